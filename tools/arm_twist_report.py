"""Whether an arm's twist is what holds a frame off: the figures of docs/accuracy.md, "Folded
arms twisted".

    python tools/arm_twist_report.py RESULT SEQUENCE --frame N [--arm right_arm]

RESULT is a `mocap fit` result folder of SEQUENCE, which must have truth.jsonl. For frame N
prints, each as energy (pixels) and mean / worst joint error (mm):
- the fit kept, and tracking's fit where refinement replaced it (``first_pass``);
- the truth's basin: the frame fitted from the truth;
- the refinement's twists stage (``common.search``: both arms' twists, the whole body fitted
  from the best) run from the fit kept and from tracking's fit;
- the arm's seven twists (``arm_twists``), each fitted as a whole body, with the elbow bent as
  the start had it (at most ``--folded`` rad) and half unfolded (``ARM_TWIST_UNFOLDED_RAD``).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common.body import CHAINS, forward_kinematics, load_body_model  # noqa: E402
from common.fitting import FitOptions, FrameResult, fit_rounds, full_energy  # noqa: E402
from common.frame import FrameData  # noqa: E402
from common.proposals import ARM_CHAINS, ARM_TWIST_UNFOLDED_RAD, arm_twists  # noqa: E402
from common.search import VARIANTS, Context, Schedule, Stage, run_schedule, solve_locally  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from common.scoring import joint_errors_mm  # noqa: E402
from server.results import load_records  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("result", type=Path)
    p.add_argument("sequence", type=Path)
    p.add_argument("--frame", type=int, required=True)
    p.add_argument("--arm", choices=ARM_CHAINS, default="right_arm")
    p.add_argument("--folded", type=float, default=2.4, help="the elbow's bend for the twists 'as it was', rad")
    args = p.parse_args(argv)

    model = load_body_model()
    records = {r["frame"]: r for r in load_records(args.result)}
    up = records[args.frame].get("world_up", "+z")
    seq = load_sequence(args.sequence, up=up)
    truth = seq.truth()[args.frame]
    data = FrameData(model, seq.studio, seq.cleaned(args.frame)[0])
    options = FitOptions()
    dispatch = solve_locally(model, data, options)
    deep = VARIANTS["deep"](options)

    def line(name: str, params: np.ndarray, energy: float | None = None) -> None:
        errors = joint_errors_mm(forward_kinematics(model, params).joints[0], truth)
        energy = full_energy(model, data, params) if energy is None else energy
        print(f"{name:44s} {int(energy):7d} pixels  {errors.mean():6.1f} / {errors.max():6.1f} mm")

    kept = np.asarray(records[args.frame]["params"], dtype=np.float64)
    line("the fit kept", kept)
    tracked = records[args.frame].get("first_pass")
    starts = [("the fit kept", kept)]
    if tracked:
        starts.append(("tracking's fit", np.asarray(tracked["params"], dtype=np.float64)))
        line("tracking's fit", starts[-1][1])
    basin = fit_rounds(model, data, truth.params, deep, dispatch)
    line("the truth's basin (fitted from the truth)", basin.params, basin.energy)
    for name, x in starts:
        initial = FrameResult(x, full_energy(model, data, x), 0, 0)
        ctx = Context(model, data, options, dispatch)
        best = run_schedule(ctx, Schedule((Stage(("twists",), ("deep",)),)), initial=initial)
        line(f"the twists stage from {name}", best.params, best.energy)
    elbow = CHAINS[args.arm].params[3]
    for label, bend in (("as it was", min(kept[elbow], args.folded)), ("half unfolded", ARM_TWIST_UNFOLDED_RAD)):
        for k, start in enumerate(arm_twists(model, args.arm, kept), start=1):
            start[elbow] = bend
            fitted = fit_rounds(model, data, start, deep, dispatch)
            line(f"{args.arm} twist {k}/7, elbow {label} ({bend:.2f} rad)", fitted.params, fitted.energy)
    return 0


if __name__ == "__main__":
    sys.exit(main())
