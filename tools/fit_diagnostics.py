"""Why a fitted run is off where it is: energies against the truth's, lag, late frames.

    python tools/fit_diagnostics.py RESULT SEQUENCE [--every 5] [--restart-at N] [--chains F1,F2,...]

RESULT is a `mocap fit` result folder of SEQUENCE, which must have truth.jsonl. Prints:
- per frame (every --every frames): the fit's energy, the truth's energy and the error. Where
  the truth's energy is lower, better search would help; where it is higher, the energy itself
  prefers the wrong pose;
- lag: the root's error along its direction of motion and the angles' error along the sign of
  their velocity (negative: the fit trails the actor), against the motion per frame;
- with --restart-at N: the frames from N on fitted again from the truth of frame N, so that
  late frames' error can be told apart from error that grows with tracking time (drift);
- with --chains F1,F2,...: for each of these frames, the frame fitted from the truth (does
  the truth's basin hold, and how much lower is it?) and the energy change of the fit with
  each chain alone put at the truth's pose. Where every change is positive while the truth's
  basin is lower, the torso and limbs are off together: no chain can move alone. A second
  line per frame gives the fewest chains that, put at the truth together, lower the energy;
  the highest energy on the straight line (in all 35 parameters) from the fit to the truth,
  over the fit's (0: the energy never rises on the way, the valley is there but runs across
  the chains); and the frame fitted from halfway between its neighbours' fits, as a
  refinement pass does.
"""
from __future__ import annotations

import argparse
import itertools
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common.body import CHAINS, P, forward_kinematics, load_body_model  # noqa: E402
from common.energy import whole_energy  # noqa: E402
from common.fitting import FitOptions, FrameData, full_energy  # noqa: E402
from common.proposals import midway, same_pose_near  # noqa: E402
from common.search import fit_frame  # noqa: E402
from common.sequence import load_sequence, write_sequence_meta  # noqa: E402
from common.scoring import joint_errors_mm  # noqa: E402
from server.results import load_records, read_foreground_left_out  # noqa: E402
from server.session import LocalSolver, run_fit  # noqa: E402

WINDOW = 20  # frames in the first and last windows of the drift comparison
LINE_POINTS = 11  # poses on the straight line from a fit to the truth, both ends included


def joint_error_mm(model, params, truth_frame) -> float:
    """Mean joint error of a (35,) pose against a TruthFrame, mm."""
    return float(joint_errors_mm(forward_kinematics(model, np.asarray(params)).joints[0], truth_frame).mean())


def energies_against_truth(model, seq, truth, records, every: int, as_segmented=None) -> None:
    """Per frame: the fit's energy and the truth's, against ``seq``'s masks (the cleared ones
    where the fit cleared foreground), and then the share of the true body's silhouette pixels
    that were cleared (``as_segmented``: the sequence with its masks as segmented)."""
    lower = 0
    for r in records[::every]:
        data = FrameData(model, seq.studio, seq.silhouettes(r["frame"]))
        t = truth[r["frame"]]
        e_truth = full_energy(model, data, t.params)
        lower += e_truth < r["energy"]
        line = (f"frame {r['frame']:5d}  fit {r['energy']:7d}  truth {e_truth:7d}  "
                f"{100.0 * (r['energy'] - e_truth) / e_truth:+5.1f}%  "
                f"error {joint_error_mm(model, r['params'], t):5.1f} mm")
        if as_segmented is not None:
            segmented = FrameData(model, seq.studio, as_segmented.silhouettes(r["frame"]))
            body = segmented.whole_image_energy().render(np.asarray(t.params)) & segmented.masks
            line += f"  the true body's mask cleared {np.count_nonzero(body & ~data.masks) / max(body.sum(), 1):.1%}"
        print(line)
    print(f"the truth's energy is lower in {lower} of {len(records[::every])} frames")


def lag(truth, records) -> None:
    if len(records) < 3:  # a velocity needs neighbours on both sides
        return
    X = np.array([r["params"] for r in records])
    T = np.array([truth[r["frame"]].params for r in records])
    velocity = np.gradient(T[:, :3], axis=0)
    speed = np.linalg.norm(velocity, axis=1)
    along = ((X[:, :3] - T[:, :3]) * velocity).sum(axis=1) / np.maximum(speed, 1e-9)
    angular = np.gradient(T[:, 3:], axis=0)
    print(f"root error along its motion: {1000 * along.mean():+.1f} mm (moving {1000 * speed.mean():.1f} mm/frame)")
    print(f"angle error along its velocity: {((X[:, 3:] - T[:, 3:]) * np.sign(angular)).mean():+.4f} rad "
          f"(moving {np.abs(angular).mean():.4f} rad/frame)")


def restart_from_truth(model, seq, records, start: int, options: FitOptions) -> None:
    frames = [r["frame"] for r in records]
    if start not in frames[1:]:
        raise SystemExit(f"--restart-at {start}: not a fitted frame after the first")
    k = frames.index(start)
    with tempfile.TemporaryDirectory() as tmp:
        part = Path(tmp) / "sequence"
        part.mkdir()
        write_sequence_meta(part, frames[k:], seq.fps, seq.studio.names)
        for name in ("calibration.json", "truth.jsonl"):
            shutil.copy(seq.path / name, part / name)
        (part / "silhouettes").symlink_to((seq.path / "silhouettes").resolve())
        again = run_fit(model, load_sequence(part), Path(tmp) / "result", options, LocalSolver(model, options),
                        init="truth")
    late = again["per_frame_error_mm"][-WINDOW:]
    whole = [r for r in records if r["frame"] in frames[-WINDOW:]]
    truth = seq.truth()
    tracked = [joint_error_mm(model, r["params"], truth[r["frame"]]) for r in whole]
    print(f"last {WINDOW} frames: {np.mean(tracked):.1f} mm tracked from frame {frames[0]}, "
          f"{np.mean(late):.1f} mm tracked from the truth at frame {start}")


def chains_against_truth(model, seq, truth, records, frames: list[int], options: FitOptions) -> None:
    by_frame = {r["frame"]: r for r in records}
    missing = [f for f in frames if f not in by_frame]
    if missing:
        raise SystemExit(f"--chains {missing[0]}: not a fitted frame")
    for f in frames:
        r, t = by_frame[f], truth[f]
        data = FrameData(model, seq.studio, seq.silhouettes(f))
        fit = np.asarray(r["params"])
        energy = full_energy(model, data, fit)
        from_truth = fit_frame(model, data, t.params, options)
        swaps = []
        for name, chain in CHAINS.items():
            swapped = fit.copy()
            swapped[list(chain.params)] = t.params[list(chain.params)]
            swaps.append(f"{name} {full_energy(model, data, swapped) - energy:+d}")
        print(f"frame {f:5d}  fit {energy:7d} ({joint_error_mm(model, fit, t):.1f} mm)  fitted from the truth "
              f"{from_truth.energy:7d} ({joint_error_mm(model, from_truth.params, t):.1f} mm)  "
              f"one chain at the truth: {', '.join(swaps)}")
        whole = data.whole_image_energy()
        target = same_pose_near(t.params, fit)
        names, change = fewest_chains_lowering(whole, fit, target, energy)
        line = whole(fit[None] + np.linspace(0.0, 1.0, LINE_POINTS)[:, None] * (target - fit)[None])
        fewest = f"{'+'.join(names)} {change:+d}" if names else "none"
        text = (f"frame {f:5d}  fewest chains at the truth that lower it: {fewest}  "
                f"straight line to the truth: highest {whole_energy(line.max()) - energy:+d}")
        if f - 1 in by_frame and f + 1 in by_frame:
            halfway = fit_frame(model, data, midway(by_frame[f - 1]["params"], by_frame[f + 1]["params"]), options)
            text += (f"  fitted from halfway between frames {f - 1} and {f + 1}: {halfway.energy} "
                     f"({joint_error_mm(model, halfway.params, t):.1f} mm)")
        print(text)


def fewest_chains_lowering(energy, fit: np.ndarray, truth_params: np.ndarray, fit_energy: int) -> tuple:
    """(chain names, energy change) of the fewest chains that, put at ``truth_params`` (35,)
    together, lower ``energy`` below ``fit_energy`` the most among sets of that size; ((), 0)
    where none does."""
    for size in range(1, len(CHAINS) + 1):
        sets = list(itertools.combinations(CHAINS, size))
        poses = np.repeat(np.asarray(fit, dtype=np.float64)[None], len(sets), axis=0)
        for pose, names in zip(poses, sets):
            for name in names:
                pose[list(CHAINS[name].params)] = truth_params[list(CHAINS[name].params)]
        changes = energy(poses) - fit_energy
        best = int(np.argmin(changes))
        if changes[best] < 0:
            return sets[best], whole_energy(changes[best])
    return (), 0


def frame_list(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected frame numbers separated by commas, got {text!r}") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("result", type=Path)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--every", type=int, default=5, help="energies of every N-th frame (default 5)")
    ap.add_argument("--restart-at", type=int, default=None, metavar="FRAME")
    ap.add_argument("--chains", type=frame_list, default=[], metavar="F1,F2,...",
                    help="these frames fitted from the truth, and each chain alone put at the truth")
    args = ap.parse_args(argv)
    summary = json.loads((args.result / "summary.json").read_text())
    model = load_body_model().scaled(summary.get("actor_scale", 1.0))  # the actor the run fitted
    seq = as_segmented = load_sequence(args.sequence)
    cleared = read_foreground_left_out(args.result)
    if cleared is not None:  # the records' energies are against the masks the fit cleared
        seq = as_segmented.without_foreground(cleared)
        print(f"against the masks the fit used: {summary['foreground_left_out']['share']:.1%} of the silhouette "
              "area cleared")
    truth = seq.truth()
    if not truth:
        raise SystemExit(f"{args.sequence}: no truth.jsonl")
    records = load_records(args.result)
    # the run's own options, so that the restart fits as the run did
    options = FitOptions.from_wire(summary["options"])
    energies_against_truth(model, seq, truth, records, args.every, as_segmented if cleared is not None else None)
    lag(truth, records)
    errors = [joint_error_mm(model, r["params"], truth[r["frame"]]) for r in records]
    print(f"first {WINDOW} / last {WINDOW} frames: {np.mean(errors[:WINDOW]):.1f} / {np.mean(errors[-WINDOW:]):.1f} mm")
    if args.chains:
        chains_against_truth(model, seq, truth, records, args.chains, options)
    if args.restart_at is not None:
        restart_from_truth(model, seq, records, args.restart_at, options)
    return 0


if __name__ == "__main__":
    sys.exit(main())
