"""``mocap bench batch``: a project's throughput with ``mocap batch`` against a serial loop of
``mocap run``, on the same takes (virtual-studio walks from several starts, default settings).

Both sides run the real commands as separate processes, so each pays what a user pays
(interpreter start, imports, compiled-code cache); the ratio of their wall times is the
batch's throughput gain. Poses must be equal: a batch changes where takes run, not results.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common.body import load_body_model
from common.camera import circle_studio
from common.synth import SynthOptions, synthesize

REPO = Path(__file__).resolve().parents[1]
TAKE_START_STEP = 40  # source frames between the takes' first frames (different motion per take)
TARGET_SPEEDUP = 1.8  # the batch issue's target on 2 cores with 2 workers


def _mocap(*argv) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "server.cli", *map(str, argv)], cwd=REPO, check=True,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def make_project(root: Path, takes: int, frames: int) -> Path:
    from server.commands.synth import DEFAULT_CLIP

    model, studio = load_body_model(), circle_studio()
    root.mkdir(parents=True)
    (root / "Config.toml").write_text("[report]\ngif = false\n")
    for i in range(takes):
        synthesize(model, studio, DEFAULT_CLIP, root / f"take{i + 1}",
                   SynthOptions(frames=frames, start=1 + i * TAKE_START_STEP, noise="cheung", seed=i))
    return root


def _poses(project: Path) -> dict:
    return {t.name: [json.loads(line)["params"] for line in (t / "result" / "poses.jsonl").read_text().splitlines()]
            for t in sorted(project.iterdir()) if (t / "result" / "poses.jsonl").is_file()}


def bench_batch(takes: int = 4, frames: int = 20, workers: int = 2, workdir: Path | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
        root = Path(workdir or tmp)
        serial = make_project(root / "serial", takes, frames)
        batched = root / "batch"
        shutil.copytree(serial, batched)
        serial_seconds = sum(_mocap("run", t) for t in sorted(p for p in serial.iterdir() if p.is_dir()))
        batch_seconds = _mocap("batch", batched, "--workers", workers, "--quiet")
        same = _poses(serial) == _poses(batched)
        record = json.loads((batched / "batch.json").read_text())
    return {"takes": takes, "frames_per_take": frames, "workers": workers,
            "serial_seconds": serial_seconds, "batch_seconds": batch_seconds,
            "serial_frames_per_second": takes * frames / serial_seconds,
            "batch_frames_per_second": takes * frames / batch_seconds,
            "speedup": serial_seconds / batch_seconds, "target_speedup": TARGET_SPEEDUP,
            "same_poses": same, "statuses": sorted({t["status"] for t in record["takes"]})}
