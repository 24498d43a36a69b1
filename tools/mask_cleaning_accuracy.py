"""Accuracy with and without the multi-view mask cleaning on the shared CMU clips.

    python tools/mask_cleaning_accuracy.py --frames 40 --out DIR [--part 1/2] [--clips A.bvh ...]

Each clip (../shared/data/mocap/*/*.bvh, natural order) is synthesised from frame 1 in the
default 8-camera studio with Cheung noise, then fitted from the truth's first pose with the
default options twice: masks as synthesised (``clean_masks=False``) and cleaned (the default).
Prints a row per clip (mean / max joint error, mm, and tracking seconds per frame) and writes
DIR/cleaning-PART.json. ``--part K/N`` takes every N-th clip from the K-th, so that N processes
can share the work.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common.body import load_body_model  # noqa: E402
from common.camera import circle_studio  # noqa: E402
from common.fitting import FitOptions  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from common.synth import SynthOptions, synthesize  # noqa: E402
from server.benchmarks import shared_clips  # noqa: E402
from server.session import LocalSolver, run_fit  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--part", default="1/1", help="K/N: every N-th clip from the K-th")
    ap.add_argument("--clips", nargs="*", type=Path, help="BVH files (default: the shared clips)")
    args = ap.parse_args()
    k, n = (int(v) for v in args.part.split("/"))
    clips = (args.clips or shared_clips())[k - 1::n]
    model, options = load_body_model(), FitOptions()
    rows = []
    for clip in clips:
        seq_dir = args.out / f"seq-{clip.stem}"
        if not (seq_dir / "sequence.json").exists():
            synthesize(model, circle_studio(), clip, seq_dir, SynthOptions(frames=args.frames, start=1, noise="cheung", seed=0))
        row = {"clip": clip.name}
        for label, clean in (("raw", False), ("cleaned", True)):
            seq = load_sequence(seq_dir, clean_masks=clean)
            s = run_fit(model, seq, args.out / f"result-{clip.stem}-{label}", options, LocalSolver(model, options),
                        init="truth")
            row[label] = {"mean_mm": s["mean_joint_error_mm"], "max_mm": s["max_joint_error_mm"],
                          "seconds_per_frame": s["seconds_per_frame"]}
        rows.append(row)
        r, c = row["raw"], row["cleaned"]
        print(f"{clip.name:28s} raw {r['mean_mm']:6.1f} / {r['max_mm']:6.1f}  cleaned {c['mean_mm']:6.1f} / "
              f"{c['max_mm']:6.1f} mm  s/frame {r['seconds_per_frame']:.2f} / {c['seconds_per_frame']:.2f}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"cleaning-{k}of{n}.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
