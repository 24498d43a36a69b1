"""Frames whose energy stands above both neighbours', fitted again from their final neighbours.

    python tools/spike_refine_trial.py RESULT SEQUENCE [RESULT SEQUENCE ...] [--ratio 1.08]

A single backward refinement pass fits each frame from the frame after it (already refined)
and from halfway to the frame before it, whose fit is still tracking's. A frame that tracking
left far off between two good ones can then keep its bad fit (05_17 from source frame 401 with
other noise, frame 80: 428.8 mm, while halfway between its final neighbours fits 4% lower and
15.8 mm off on average). This trial finds, in finished results, the frames whose energy is
``--ratio`` times the mean of their two neighbours' or more, fits each again by the refinement
schedule (``common.search.refine_frame``) from its final neighbour before it, with the one after
as the other side, and prints for each its energy and worst joint before and after (with truth).
The results are not changed: it says what such a step after the passes would do, and costs.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common.body import forward_kinematics, load_body_model  # noqa: E402
from common.fitting import FitOptions, FrameData, FrameResult  # noqa: E402
from common.scoring import joint_errors_mm  # noqa: E402
from common.search import STANDING_OUT_RATIO, refine_frame, solve_locally, standing_out  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from server.results import load_records  # noqa: E402

def worst_mm(model, params, truth_frame) -> float:
    return float(joint_errors_mm(forward_kinematics(model, np.asarray(params)).joints[0], truth_frame).max())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="+", type=Path, help="RESULT SEQUENCE, repeated")
    ap.add_argument("--ratio", type=float, default=STANDING_OUT_RATIO)
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        print("give RESULT SEQUENCE pairs", file=sys.stderr)
        return 2
    options = FitOptions()
    count = fixed = worse = 0
    for result, sequence in zip(args.pairs[::2], args.pairs[1::2]):
        seq = load_sequence(sequence)
        records = load_records(result)
        scale = json.loads((result / "summary.json").read_text()).get("actor_scale", 1.0)
        model = load_body_model() if scale == 1.0 else load_body_model().scaled(scale)
        truth = seq.truth()
        for i in standing_out([r["energy"] for r in records], args.ratio):
            r, before, after = records[i], records[i - 1], records[i + 1]
            data = FrameData(model, seq.studio, seq.silhouettes(r["frame"]))
            fit = FrameResult(np.asarray(r["params"], dtype=np.float64), int(r["energy"]), 0, 0)
            t0 = time.perf_counter()
            again = refine_frame(model, data, fit, options, solve_locally(model, data, options, r["frame"]),
                                 np.asarray(before["params"]), None, np.asarray(after["params"]),
                                 frame_number=r["frame"])
            seconds = time.perf_counter() - t0
            count += 1
            line = (f"{result.name} frame {r['frame']}: energy {r['energy']} -> {again.energy} "
                    f"({again.energy / r['energy'] - 1:+.1%}), {seconds:.1f} s")
            t = truth.get(r["frame"])
            if t is not None:
                w0, w1 = worst_mm(model, r["params"], t), worst_mm(model, again.params, t)
                fixed += w0 > 40.0 >= w1
                worse += w1 > 40.0 >= w0
                line += f", worst joint {w0:.1f} -> {w1:.1f} mm"
            print(line, flush=True)
    print(f"{count} frames standing out; over 40 mm before and not after: {fixed}; the other way: {worse}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
