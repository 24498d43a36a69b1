"""Joint error against the number of cameras: the figures behind ``mocap fit``'s warning for
fewer than 3 cameras (docs/accuracy.md, "Fewer cameras").

    python tools/camera_count_accuracy.py [--cameras 1,2,3,4,8] [--frames 20] [--work DIR]

Each count: ``mocap synth`` of the bundled walk (ring cameras, Cheung noise, seed 0), then
``mocap fit`` with the default settings from the truth's first pose; prints one row per count.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path


def mocap(*argv) -> None:
    subprocess.run([sys.executable, "-m", "server.cli", *map(str, argv)], check=True,
                   cwd=Path(__file__).resolve().parents[1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", default="1,2,3,4,8")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--work", type=Path, default=None, help="keep the sequences and results here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="camera-count-") as tmp:
        work = (args.work or Path(tmp)).resolve()
        print(f"{'cameras':>7}  {'mean mm':>8}  {'max mm':>8}  {'wall s':>7}")
        for n in (int(v) for v in args.cameras.split(",")):
            seq, out = work / f"seq-{n}", work / f"result-{n}"
            mocap("synth", "--out", seq, "--cameras", n, "--frames", args.frames, "--noise", "cheung", "--quiet",
                  "--overwrite")
            mocap("fit", seq, "--out", out, "--quiet", "--overwrite")
            s = json.loads((out / "summary.json").read_text())
            print(f"{n:>7}  {s['mean_joint_error_mm']:>8.1f}  {s['max_joint_error_mm']:>8.1f}  {s['wall_seconds']:>7.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
