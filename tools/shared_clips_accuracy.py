"""Accuracy and time on every shared clip: the check every accuracy change is measured by.

    python tools/shared_clips_accuracy.py [--frames 100] [--jobs 2] [--preset default]
                                          [--init truth|auto] [--seed 0] [--start 1] [--json FILE]
                                          [--work DIR] [--fit-args "--refine-chunk-frames 10"]

Each clip of ../shared/data/mocap (17) is synthesised into the 8-camera 320x240 studio with
Cheung noise (``--seed``, default 0: another seed draws other noise, to tell a change's effect
from chance), then fitted single-process with the preset's settings from the truth's
first pose (``--init auto``: from a search of the first frame), as ``mocap bench accuracy``
fits its three clips, with any further ``mocap fit`` options (``--fit-args``). Clips run
``--jobs`` at a time, one process each, the cores shared among them (``--threads``). Prints one row per
clip (mean and worst joint error, frames with a joint over 40 mm, seconds per frame) and
writes them as JSON.

``--start N`` synthesises each clip from source frame N instead of 1 (every 4th source frame is
one frame at 30 fps), skipping the clips too short to give ``--frames`` frames from there (from
frame 1 a short clip gives the frames it has):
``--start 401`` fits the 100 frames after those of the default run, motion that no setting
was ever tried on.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from server.benchmarks import MAX_ERROR_TARGET_MM, shared_clips, write_json  # noqa: E402
from server.threads import usable_cores  # noqa: E402


SOURCE_STEP = 4  # source frames (120 fps) per synthesised frame (30 fps): SynthOptions' default


def fit_clip(clip: Path, frames: int, work: Path, preset: str, init: str, fit_args: tuple = (),
             threads: int = 1, seed: int = 0, start: int = 1) -> dict:
    from common.body import load_body_model
    from common.camera import circle_studio
    from common.sequence import load_sequence
    from common.synth import SynthOptions, synthesize
    from server.cli import main as mocap

    named = clip.stem + (f"-seed{seed}" if seed else "") + (f"-from{start}" if start != 1 else "")
    seq_dir = work / f"seq-{named}"
    if not (seq_dir / "sequence.json").exists():
        synthesize(load_body_model(), circle_studio(), clip, seq_dir,
                   SynthOptions(frames=frames, noise="cheung", seed=seed, start=start, step=SOURCE_STEP))
    out = work / (f"fit-{named}-{preset}-{init}" + "".join(fit_args).replace("-", "_"))
    t0 = time.perf_counter()
    code = mocap(["fit", str(seq_dir), "--out", str(out), "--preset", preset, "--init", init, "--frames", str(frames),
                  "--threads", str(threads), "--quiet", "--overwrite", *fit_args])
    wall = time.perf_counter() - t0
    if code:
        raise RuntimeError(f"mocap fit {seq_dir} failed ({code})")
    s = json.loads((out / "summary.json").read_text())
    load_sequence(seq_dir)  # readable, as the fit found it
    return {"clip": clip.stem, "frames": s["frames"], "preset": preset, "init": init,
            "mean_joint_error_mm": s["mean_joint_error_mm"], "max_joint_error_mm": s["max_joint_error_mm"],
            "frames_over_40mm": sum(v > MAX_ERROR_TARGET_MM for v in s["per_frame_max_error_mm"]),
            "worst_frame": int(max(range(s["frames"]), key=lambda k: s["per_frame_max_error_mm"][k])),
            "tracking_mean_joint_error_mm": s["tracking_mean_joint_error_mm"],
            "tracking_max_joint_error_mm": s["tracking_max_joint_error_mm"],
            "wall_seconds_per_frame": wall / s["frames"], "seconds_per_frame": s["mean_seconds_per_frame"],
            "refine_seconds_per_frame": s["refine_seconds_per_frame"]}


def source_frames(clip: Path) -> int:
    """The frames a BVH clip holds (its MOTION section's ``Frames:`` line)."""
    with open(clip, encoding="utf-8", errors="replace") as f:
        for line in f:
            if line.strip().lower().startswith("frames:"):
                return int(line.split(":", 1)[1])
    raise ValueError(f"{clip}: no Frames: line")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--preset", default="default")
    ap.add_argument("--init", default="truth", choices=("truth", "auto"))
    ap.add_argument("--clips", default=None, help="comma-separated clip stems (default: all shared clips)")
    ap.add_argument("--fit-args", default="", help="further mocap fit options, one string")
    ap.add_argument("--seed", type=int, default=0, help="the synthesised noise's seed")
    ap.add_argument("--start", type=int, default=1, help="the first source frame (default 1)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--work", type=Path, default=None, help="keep the sequences and results here")
    args = ap.parse_args(argv)
    clips = shared_clips()
    if args.clips:
        clips = [c for c in clips if c.stem in args.clips.split(",")]
    if args.start < 1:
        print(f"--start: must be 1 or more, got {args.start}", file=sys.stderr)
        return 2
    # from the start, a short clip gives the frames it has (06_08: 86); from later, those it lacks
    # would be another clip's count
    long_enough = [c for c in clips
                   if args.start == 1 or source_frames(c) >= args.start + SOURCE_STEP * (args.frames - 1) + 1]
    if len(long_enough) < len(clips):
        print(f"skipped, shorter than {args.frames} frames from source frame {args.start}: "
              f"{', '.join(c.stem for c in clips if c not in long_enough)}", file=sys.stderr)
    clips = long_enough
    if not clips:
        print("no shared clips (../shared/data/mocap)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="shared-clips-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        with ProcessPoolExecutor(args.jobs) as pool:
            n = len(clips)
            threads = max(1, usable_cores() // args.jobs)
            rows = list(pool.map(fit_clip, clips, [args.frames] * n, [work] * n, [args.preset] * n, [args.init] * n,
                                 [tuple(args.fit_args.split())] * n, [threads] * n, [args.seed] * n,
                                 [args.start] * n))
    print(f"{'clip':16s} {'mean':>6s} {'max':>6s} {'>40':>4s} {'worst':>5s} {'s/frame':>8s} {'refine':>7s} {'wall':>6s}")
    for r in rows:
        print(f"{r['clip']:16s} {r['mean_joint_error_mm']:6.1f} {r['max_joint_error_mm']:6.1f} "
              f"{r['frames_over_40mm']:4d} {r['worst_frame']:5d} {r['seconds_per_frame']:8.3f} "
              f"{r['refine_seconds_per_frame']:7.3f} {r['wall_seconds_per_frame']:6.3f}")
    means = [r["mean_joint_error_mm"] for r in rows]
    print(f"all {len(rows)}: mean {sum(means) / len(means):.2f} mm, worst {max(r['max_joint_error_mm'] for r in rows):.1f} "
          f"mm, clips with a frame over 40 mm: {sum(r['frames_over_40mm'] > 0 for r in rows)}, wall "
          f"{sum(r['wall_seconds_per_frame'] for r in rows) / len(rows):.3f} s/frame")
    if args.json:
        write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
