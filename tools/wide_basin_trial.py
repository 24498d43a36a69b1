"""Does a wider-basin energy keep tracking on a fast turn? A trial, not part of the fit.

    python tools/wide_basin_trial.py SEQUENCE --first 20 --last 60 [--levels -2,0,2,5] [--wide]
    python tools/wide_basin_trial.py SEQUENCE --frames 30,33,47 --result RESULT [--levels ...]

SEQUENCE must have truth.jsonl. Tracks frames first+1 .. last-1 from the truth of frame
``first`` with the TRACKING schedule alone (no loss detection, no refinement), each frame from
the previous frame's fit, and prints each frame's energy and joint error (mean / worst, mm),
then the mean, the frames with a joint over 40 mm and the seconds.

With --wide each frame is also fitted against a blurred silhouette, then polished against the
real one, and that fit is kept where its XOR energy is lower. The blurred silhouette is a stack
of level sets: the masks eroded (negative) or dilated (positive) by each of ``--levels`` pixels,
each level a copy of the studio's cameras, so the energy is the sum of the XOR against every
level: the L1 distance between the model's silhouette and a silhouette blurred into as many
grey steps. A part that misses its silhouette by a few pixels then still pays less the nearer
it is, where the plain XOR is flat.

With --frames and --result (a ``mocap fit`` result of SEQUENCE), each of those frames is fitted
alone, from the result's fit of the frame before and from the truth of the frame before: by
tracking against the real silhouette, and against the blurred one then polished. Prints the
frame's fit in the result and the truth's energy beside each, so that a fit can be told from
the truth's basin.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common.body import forward_kinematics, load_body_model  # noqa: E402
from common.camera import Studio  # noqa: E402
from common.fitting import FitOptions, FrameData, full_energy  # noqa: E402
from common.scoring import joint_errors_mm  # noqa: E402
from common.search import fit_frame  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from server.results import load_records  # noqa: E402

OFF_MM = 40.0  # a frame with a joint this far off counts as off (issue 27's line)


def level_sets(masks: np.ndarray, levels: list[int]) -> np.ndarray:
    """(K, H, W) bool -> (L K, H, W): the masks eroded (level < 0) or dilated (> 0) by |level|
    pixels (city-block steps), level by level."""
    out = []
    for level in levels:
        if level == 0:
            out.append(masks)
        else:
            grow = ndimage.binary_dilation if level > 0 else ndimage.binary_erosion
            out.append(np.stack([grow(m, iterations=abs(level)) for m in masks]))
    return np.concatenate(out)


def blurred_frame(model, studio: Studio, masks: np.ndarray, levels: list[int]) -> FrameData:
    """A frame whose XOR energy is summed over the level sets: the studio's cameras once per level."""
    cams = tuple(replace(c, name=f"{c.name}@{level}") for level in levels for c in studio)
    return FrameData(model, Studio(cams, studio.source), level_sets(masks, levels))


def frames_alone(seq, model, result: Path, frames: list[int], levels: list[int]) -> None:
    """``--frames``: each frame fitted from the frame before's fit and truth (module docstring)."""
    truth = seq.truth()
    options = FitOptions()
    records = {r["frame"]: r for r in load_records(result)}

    def error(params, f):
        errors = joint_errors_mm(forward_kinematics(model, params).joints[0], truth[f])
        return f"{errors.mean():.1f} / {errors.max():.1f} mm"
    for f in frames:
        masks = seq.silhouettes(f)
        data = FrameData(model, seq.studio, masks)
        blurred = blurred_frame(model, seq.studio, masks, levels)
        fit = np.asarray(records[f]["params"])
        print(f"frame {f}: the result's fit {full_energy(model, data, fit)} pixels, {error(fit, f)}; "
              f"the truth {full_energy(model, data, truth[f].params)} pixels")
        for name, start in (("the fit before", np.asarray(records[f - 1]["params"])),
                            ("the truth before", truth[f - 1].params)):
            plain = fit_frame(model, data, start, options)
            wide = fit_frame(model, data, fit_frame(model, blurred, start, options).params, options)
            print(f"  from {name}: tracked {plain.energy} pixels, {error(plain.params, f)}; "
                  f"blurred then polished {wide.energy}, {error(wide.params, f)}", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--first", type=int, help="frame whose truth starts the tracking")
    ap.add_argument("--last", type=int, help="tracking stops before this frame")
    ap.add_argument("--frames", help="instead: these frames fitted alone (comma-separated), with --result")
    ap.add_argument("--result", type=Path, help="a mocap fit result of SEQUENCE, for --frames")
    ap.add_argument("--levels", default="-2,0,2,5", help="erosions (<0) and dilations (>0), pixels")
    ap.add_argument("--wide", action="store_true", help="also fit against the blurred silhouette")
    args = ap.parse_args(argv)
    seq = load_sequence(args.sequence)
    truth = seq.truth()
    model = load_body_model()
    options = FitOptions()
    levels = [int(v) for v in args.levels.split(",")]
    if args.frames:
        if args.result is None:
            ap.error("--frames needs --result")
        frames_alone(seq, model, args.result, [int(v) for v in args.frames.split(",")], levels)
        return
    if args.first is None or args.last is None:
        ap.error("--first and --last, or --frames and --result")
    start, before = truth[args.first].params, None
    means, off, kept_wide = [], 0, 0
    t0 = time.perf_counter()
    for f in range(args.first + 1, args.last):
        masks = seq.silhouettes(f)
        data = FrameData(model, seq.studio, masks)
        fit = fit_frame(model, data, start, options, before=before)
        if args.wide:
            blurred = fit_frame(model, blurred_frame(model, seq.studio, masks, levels), start, options, before=before)
            polished = fit_frame(model, data, blurred.params, options, before=before)
            if polished.energy < fit.energy:
                fit, kept_wide = polished, kept_wide + 1
        errors = joint_errors_mm(forward_kinematics(model, fit.params).joints[0], truth[f])
        means.append(float(errors.mean()))
        off += bool(errors.max() > OFF_MM)
        print(f"frame {f:4d}  energy {fit.energy:6d}  {errors.mean():5.1f} / {errors.max():5.1f} mm", flush=True)
        before, start = start, fit.params
    kept = f", the blurred fit kept in {kept_wide}" if args.wide else ""
    print(f"{'blurred and plain' if args.wide else 'plain'}: {np.mean(means):.2f} mm mean, {off} of {len(means)} "
          f"frames over {OFF_MM:.0f} mm{kept}, {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
