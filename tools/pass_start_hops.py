"""Hop by hop, what a refinement pass's first frame gains from its hops (``PASS_START_HOPS``).

    python tools/pass_start_hops.py WORK [--clips 01_01,05_13] [--hops 120] [--json FILE]

WORK: the folder of a ``tools/shared_clips_accuracy.py --work WORK`` run with the default
preset from the truth (its ``seq-<clip>`` sequences and ``fit-<clip>-default-truth`` results).
For each clip the backward pass's first frame (the last frame) is refitted as the pass refits
it (``common.search.refine_frame`` from its tracked fit, the record's "first_pass", with the
hops and the limbs' other basins), and every hop that lowers the best is listed: the hops done
so far, the best's energy, its mean and worst joint error against the truth and the
evaluations spent. The last column, the refit's energy against the run's record, says whether
the refit is the pass's own (it is deterministic). What a smaller hop count or a stop after so
many hops without gain would have kept is the last row at or before that hop.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import common.search as search  # noqa: E402  (refine_frame calls hop_fit by the name it imported)
from common.body import forward_kinematics, load_body_model  # noqa: E402
from common.fitting import FitOptions, FrameResult, hop_fit  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from common.search import PASS_START_HOPS  # noqa: E402
from server.session import frame_data  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python tools/pass_start_hops.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--clips", default=None, help="comma-separated clip stems (default: every fit in WORK)")
    ap.add_argument("--hops", type=int, default=PASS_START_HOPS)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    clips = (args.clips.split(",") if args.clips else
             sorted(p.name[len("fit-"):-len("-default-truth")] for p in args.work.glob("fit-*-default-truth")))
    if not clips:
        print(f"error: {args.work}: no fit-<clip>-default-truth results", file=sys.stderr)
        return 2
    model, options = load_body_model(), FitOptions()
    bests: list = []

    def watched_hop_fit(params, hops, options, dispatch, side_by_side=1):
        """``hop_fit`` one hop at a time (its result is that of the hops one after another),
        noting each new best."""
        best, energy, evaluations, tried = np.asarray(params, dtype=np.float64), None, 0, ()
        for done in range(hops):
            result = hop_fit(best, 1, options, _from_hop(dispatch, done), 1)
            energy = result.chains[0].energy_before if energy is None else energy
            evaluations += result.evaluations
            tried += result.chains
            if result.energy < energy:
                best, energy = result.params, result.energy
                bests.append((done + 1, int(energy), best, evaluations))
        return FrameResult(best, int(energy), hops, evaluations, tried)

    out = {}
    try:
        search.hop_fit = watched_hop_fit
        for clip in clips:
            seq = load_sequence(args.work / f"seq-{clip}")
            records = [json.loads(line) for line in (args.work / f"fit-{clip}-default-truth" / "poses.jsonl").open()]
            last = records[-1]
            tracked = last.get("first_pass", last)
            frame = last["frame"]
            truth = forward_kinematics(model, np.asarray(seq.truth()[frame].params)).joints[0]
            errors = lambda p: np.linalg.norm(forward_kinematics(model, np.asarray(p)).joints[0] - truth, axis=1) * 1e3
            data = frame_data(model, seq, frame)
            bests.clear()
            refit = search.refine_frame(model, data, FrameResult(np.asarray(tracked["params"]), int(tracked["energy"]),
                                                                 0, 0), options,
                                        search.solve_locally(model, data, options, frame), None, None, None,
                                        args.hops, True, frame, 1)
            rows = [{"hops": h, "energy": e, "mean_mm": round(float(errors(p).mean()), 1),
                     "worst_mm": round(float(errors(p).max()), 1), "evaluations": n} for h, e, p, n in bests]
            out[clip] = {"frame": frame, "tracked_energy": int(tracked["energy"]), "bests": rows,
                         "refit_energy": int(refit.energy), "recorded_energy": int(last["energy"])}
            print(f"{clip} frame {frame}: tracked {tracked['energy']}, refit {refit.energy} "
                  f"(the run's record {last['energy']})", flush=True)
            for r in rows:
                print(f"  hop {r['hops']:4d}  {r['energy']:6d} px  {r['mean_mm']:5.1f} / {r['worst_mm']:5.1f} mm  "
                      f"{r['evaluations']:8d} evaluations", flush=True)
    finally:
        search.hop_fit = hop_fit
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


def _from_hop(dispatch, done: int):
    """``dispatch`` with hop ``done`` as its iteration: the hop ``hop_fit`` would run there."""
    return lambda jobs, params, iteration, options: dispatch(jobs, params, iteration + done, options)


if __name__ == "__main__":
    sys.exit(main())
