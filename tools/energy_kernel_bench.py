"""Microseconds per evaluation of the ``cpu`` energy's compiled kernel, by kind of solve.

    python tools/energy_kernel_bench.py SEQUENCE [--frame 40] [--json FILE]

SEQUENCE: a synthesised sequence with truth (``mocap synth --out SEQUENCE``). At the truth's
pose of ``--frame`` it builds the four energies a fit evaluates most, as the fit builds them:
the torso's (whole images at half resolution, all 16 segments moving), a limb's (128-pixel
windows, 3 segments), a limb re-detection's (whole images, 3 segments) and a hand's (64-pixel
windows, 1 segment); then times ``pose_energies`` on batches of 4 poses near the truth inside
one compiled loop (no Python per call, as in the compiled Powell), best of 9 repeats.
To compare two versions, run it in each checkout one after the other: the machine's speed
drifts, so compare ratios measured close together.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common.body import CHAINS, LIMB_PARTS, load_body_model  # noqa: E402
from common.energy import ARM_WINDOW, SMALL_WINDOW, CpuEnergy, pose_energies  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from server.session import frame_data  # noqa: E402

BATCH = 4          # poses per call, as a line search's probes
CALLS = 2000       # calls per timed repeat
REPEATS = 9
SPREAD_RAD = 0.05  # joint angles drawn this far around the truth


@njit(cache=True)
def _repeat(calls, poses, tables):
    total = 0
    for _ in range(calls):
        total += pose_energies(poses, *tables)[0]
    return total


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("--frame", type=int, default=40)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    seq = load_sequence(args.sequence)
    truth = seq.truth()
    if not truth or args.frame not in truth:
        print(f"error: {args.sequence}: no truth pose for frame {args.frame}", file=sys.stderr)
        return 2
    model = load_body_model()
    data = frame_data(model, seq, args.frame)
    x = np.asarray(truth[args.frame].params, dtype=np.float64)
    arm = CHAINS["left_arm"].segments
    setups = {
        "torso (half-resolution images, 16 segments)": data.full_setup(x, half=True),
        "limb (128-pixel windows, 3 segments)": replace(data.window_setup(x, arm[:2], ARM_WINDOW, True), moving=arm),
        "re-detection (whole images, 3 segments)": replace(data.full_setup(x), moving=CHAINS["right_leg"].segments,
                                                           prerender=True),
        "hand (64-pixel windows, 1 segment)": data.window_setup(x, LIMB_PARTS["left_arm"][2], SMALL_WINDOW, True),
    }
    rng = np.random.default_rng(0)
    rows = []
    for name, setup in setups.items():
        tables = CpuEnergy(model, setup).kernel_tables
        poses = x[None] + SPREAD_RAD * rng.standard_normal((BATCH, x.size)) * (np.arange(x.size) >= 3)
        _repeat(1, poses, tables)  # compile
        best = min(_timed(poses, tables) for _ in range(REPEATS))
        rows.append({"energy": name, "us_per_evaluation": 1e6 * best / (CALLS * BATCH)})
        print(f"{name:48s} {rows[-1]['us_per_evaluation']:7.2f} us per evaluation")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


def _timed(poses, tables) -> float:
    t0 = time.perf_counter()
    _repeat(CALLS, poses, tables)
    return time.perf_counter() - t0


if __name__ == "__main__":
    sys.exit(main())
