"""Microseconds per evaluation of the ``cpu`` energy's compiled kernel, by kind of solve.

    python tools/energy_kernel_bench.py SEQUENCE [--frame 40] [--json FILE]

SEQUENCE: a synthesised sequence with truth (``mocap synth --out SEQUENCE``). At the truth's
pose of ``--frame`` it builds the energies a fit evaluates most, as the fit builds them:
the torso's (whole images at half resolution, all 16 segments moving), a limb's (128-pixel
windows, 3 segments), a limb re-detection's (whole images, 3 segments), a hand's (64-pixel
windows, 1 segment) and a hop's (whole images, all 16 segments); then times ``pose_energies``
on batches of 4 poses near the truth inside one compiled loop (no Python per call, as in the
compiled Powell), best of 9 repeats; and the grids a fit evaluates in one call: a limb's
(3 points per parameter, 81 poses) and a re-detection's (its 2,916 poses at half resolution).
Each row also says how much of an evaluation the kinematics and the conics take (the same
poses through ``pose_conics`` alone: the rest is the pixels' spans and counts), and how long building that energy takes, as a solve
builds it (the windows placed and cut, the still parts drawn, the value masks made), best of
5 runs of 200 builds. A last row times the compiled Powell (``powell_cpu``) on the limb's
energy from 200 starts about the truth, per evaluation: beside the limb's own row, what the
line searches add.
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
from common.energy import ARM_WINDOW, POSE_CHUNK, SMALL_WINDOW, CpuEnergy, pose_conics, pose_energies  # noqa: E402
from common.fitting import FitOptions  # noqa: E402
from common.powell_cpu import powell_cpu  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from server.session import frame_data  # noqa: E402

BATCH = 4          # poses per call, as a line search's probes
EVALUATIONS = 8000  # evaluations per timed repeat
REPEATS = 9
BUILDS = 200       # energy builds per timed repeat
BUILD_REPEATS = 5
SPREAD_RAD = 0.05  # joint angles drawn this far around the truth
POWELL_STARTS = 200
POWELL_SPREAD_RAD = 0.15  # the starts' spread about the truth on the arm's parameters


@njit(cache=True)
def _repeat(calls, poses, tables):
    total = 0.0
    for _ in range(calls):
        total += pose_energies(poses, *tables)[0]
    return total


@njit(cache=True)
def _repeat_conics(calls, poses, tables):
    """``pose_energies``' kinematics and conics alone (``pose_conics``), POSE_CHUNK poses at a
    time as it makes them (tables as ``CpuEnergy.kernel_tables``)."""
    total = 0.0
    for _ in range(calls):
        for c0 in range(0, poses.shape[0], POSE_CHUNK):
            t = tables  # spelled out: numba inlines pose_conics, which *args cannot reach
            C, _ = pose_conics(poses[c0:c0 + POSE_CHUNK], t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7], t[8], t[9],
                               t[10])
            total += C[0, 0, 0, 0, 0]
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
    arm, leg = CHAINS["left_arm"].segments, CHAINS["right_leg"].segments
    def limb():
        return replace(data.window_setup(x, arm[:2], ARM_WINDOW, True), moving=arm)

    def redetection(half: bool):
        return lambda: replace(data.full_setup(x, half=half), moving=leg, prerender=True)

    setups = {  # name: (the setup as a solve makes it, poses per call)
        "torso (half-resolution images, 16 segments)": (lambda: data.full_setup(x, half=True), BATCH),
        "limb (128-pixel windows, 3 segments)": (limb, BATCH),
        "re-detection (whole images, 3 segments)": (redetection(False), BATCH),
        "hand (64-pixel windows, 1 segment)": (lambda: data.window_setup(x, LIMB_PARTS["left_arm"][2], SMALL_WINDOW,
                                                                         True), BATCH),
        "hop (whole images, 16 segments)": (lambda: data.full_setup(x), BATCH),
        "limb grid (128-pixel windows, 81 poses)": (limb, 81),
        "re-detection grid (half resolution, 2916 poses)": (redetection(True), 2916),
    }
    rng = np.random.default_rng(0)
    rows = []
    for name, (setup, batch) in setups.items():
        tables = CpuEnergy(model, setup()).kernel_tables
        poses = x[None] + SPREAD_RAD * rng.standard_normal((batch, x.size)) * (np.arange(x.size) >= 3)
        calls = max(1, EVALUATIONS // batch)
        _repeat(1, poses, tables)  # compile
        _repeat_conics(1, poses, tables)
        best = min(_timed(_repeat, calls, poses, tables) for _ in range(REPEATS))
        conics = min(_timed(_repeat_conics, calls, poses, tables) for _ in range(REPEATS))
        build = min(_built(BUILDS, model, setup) for _ in range(BUILD_REPEATS))
        rows.append({"energy": name, "poses_per_call": batch, "us_per_evaluation": 1e6 * best / (calls * batch),
                     "us_kinematics_and_conics": 1e6 * conics / (calls * batch),
                     "us_per_build": 1e6 * build / BUILDS})
        print(f"{name:48s} {rows[-1]['us_per_evaluation']:7.2f} us per evaluation "
              f"({rows[-1]['us_kinematics_and_conics']:5.2f} kinematics and conics), "
              f"{rows[-1]['us_per_build']:8.1f} us per build")
    rows.append(_powell_row(model, limb(), x, rng))
    print(f"{rows[-1]['energy']:48s} {rows[-1]['us_per_evaluation']:7.2f} us per evaluation")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


def _built(builds: int, model, setup) -> float:
    t0 = time.perf_counter()
    for _ in range(builds):
        CpuEnergy(model, setup())
    return time.perf_counter() - t0


def _timed(loop, calls, poses, tables) -> float:
    t0 = time.perf_counter()
    loop(calls, poses, tables)
    return time.perf_counter() - t0


def _powell_row(model, setup, x, rng) -> dict:
    """The compiled Powell over the left arm's proximal parameters, as a limb's solve runs it."""
    options = FitOptions()
    energy = CpuEnergy(model, setup)
    idx = np.asarray(LIMB_PARTS["left_arm"][0])
    steps = np.full(len(idx), options.limb_step_rad)
    starts = [x + POWELL_SPREAD_RAD * rng.standard_normal(x.size) * np.isin(np.arange(x.size), idx)
              for _ in range(POWELL_STARTS)]
    solve = lambda start: powell_cpu(energy, start, idx, steps, options.xtol, options.ftol, options.max_evals_limb)
    solve(starts[0])  # compile
    best = np.inf
    for _ in range(3):
        energy.evaluations = 0
        t0 = time.perf_counter()
        for start in starts:
            solve(start)
        best = min(best, time.perf_counter() - t0)
    return {"energy": f"limb's Powell solves ({POWELL_STARTS} starts)", "poses_per_call": None,
            "us_per_evaluation": 1e6 * best / energy.evaluations, "evaluations": energy.evaluations}


if __name__ == "__main__":
    sys.exit(main())
