"""What the finish's evolutions gain for their budget, on a fitted run: every frame of RESULT
finished again as ``mocap fit`` finishes it (``common.search.FINISH``: evolutions over all 35
parameters, the lowest polished, kept where its energy is lower), with other numbers of
evolutions and evaluations each.

    python tools/finish_budget.py RESULT SEQUENCE [--evolutions 1,2] [--evaluations 3000,6000]

RESULT is a `mocap fit` result of SEQUENCE, which must have truth.jsonl; a finished run's frames
are finished again from where they are, so give it a run with the finish turned off
(``--set 'fit.schedules={finish_evolutions=0}'``). Prints, per setting, the mean joint error
over the frames and the mean of each frame's worst joint, before and after, the frames whose
energy fell, and the seconds per frame on one thread.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common.body import forward_kinematics, load_body_model  # noqa: E402
from common.fitting import EVOLVE_JOBS, FitOptions, FrameData, FrameResult, evolve  # noqa: E402
from common.scoring import joint_errors_mm  # noqa: E402
from common.search import SCHEDULES, finish_frame, solve_locally  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from server.results import load_records, read_foreground_left_out  # noqa: E402


def counts(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected whole numbers separated by commas, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected whole numbers >= 1, got {text!r}")
    return values


def budgeted(model, data, options, frame_number: int, evaluations: int):
    """``solve_locally``'s dispatch with every evolution given ``evaluations``."""
    local = solve_locally(model, data, options, frame_number)

    def dispatch(jobs, params, iteration, options_given=None):
        if jobs and all(j in EVOLVE_JOBS for j in jobs):
            return lambda: [evolve(model, data, params, options, iteration + EVOLVE_JOBS.index(j), frame_number, j,
                                   evaluations) for j in jobs]
        return local(jobs, params, iteration, options_given)

    return dispatch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("result", type=Path)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--evolutions", type=counts, default=[SCHEDULES.finish_evolutions])
    ap.add_argument("--evaluations", type=counts, default=[6000])
    args = ap.parse_args(argv)
    summary = json.loads((args.result / "summary.json").read_text())
    model = load_body_model().scaled(summary.get("actor_scale", 1.0))
    seq = load_sequence(args.sequence)
    cleared = read_foreground_left_out(args.result)
    if cleared is not None:  # the records' energies are against the masks the fit cleared
        seq = seq.without_foreground(cleared)
    truth = seq.truth()
    if not truth:
        raise SystemExit(f"{args.sequence}: no truth.jsonl")
    options = FitOptions.from_wire(summary["options"])
    records = load_records(args.result)
    frames = [(r, FrameData(model, seq.studio, seq.silhouettes(r["frame"]))) for r in records]

    def errors(params, frame):
        e = joint_errors_mm(forward_kinematics(model, np.asarray(params)).joints[0], truth[frame])
        return e.mean(), e.max()

    before = np.array([errors(r["params"], r["frame"]) for r, _ in frames])
    print(f"as fitted: {before[:, 0].mean():.2f} mm mean, {before[:, 1].mean():.2f} mm mean worst joint")
    for n in args.evolutions:
        for evaluations in args.evaluations:
            schedules = replace(SCHEDULES, finish_evolutions=n)
            after, lower, t0 = [], 0, time.perf_counter()
            for r, data in frames:
                fit = FrameResult(np.asarray(r["params"], dtype=np.float64), int(r["energy"]), 0, 0)
                done = finish_frame(model, data, fit, options, budgeted(model, data, options, r["frame"], evaluations),
                                    r["frame"], schedules)
                lower += done.energy < fit.energy
                after.append(errors(done.params if done.energy < fit.energy else fit.params, r["frame"]))
            after = np.array(after)
            print(f"{n} evolution(s) of {evaluations} evaluations: {after[:, 0].mean():.2f} mm mean, "
                  f"{after[:, 1].mean():.2f} mm mean worst joint; {lower} of {len(frames)} frames lower; "
                  f"{(time.perf_counter() - t0) / len(frames):.2f} s per frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
