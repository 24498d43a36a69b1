"""Benchmarks behind `make bench` and `mocap bench`: the paper's Tables 1 and 2, side by side.

Every figure is measured here, now, on this machine; the paper's figures (GeForce3, 2003) sit
beside ours in each row. Rates are evaluations per second of the XOR energy with 8 cameras.
"""
from __future__ import annotations

import copy
import json
import multiprocessing as mp
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from common.body import CHAINS, forward_kinematics, load_body_model, rest_params
from common.energy import ARM_WINDOW, SMALL_WINDOW
from common.objective import make_energy
from common.errors import UserError
from common.fitting import FitOptions, FrameData

# Theobalt et al. 2003, Table 1 (XOR / XORPR evaluations per second) and Table 2 (s/frame, seq. A)
PAPER_TABLE1 = {"full": 95.9, "half": 131.1, "arm128": 133.7, "arm128_prerender": 433.1, "head64_prerender": 855.4}
PAPER_TABLE2 = {"single_xor": 7.98, "single_xorpr": 3.30, "distributed": 1.16}
MEASURE_SECONDS = 1.5   # per rate measurement
BATCH = 16              # candidate poses per evaluation call (the optimizer's line searches batch 4-81)


def _bench_pose(model, rng) -> np.ndarray:
    p = rest_params(model, heading=0.4)
    p[6:35] += rng.normal(0.0, 0.15, 29)
    return p


def energy_setup(case: str, frame: FrameData, params: np.ndarray):
    if case == "full":
        return frame.full_setup(params)
    if case == "half":
        return frame.full_setup(params, half=True)
    if case in ("arm128", "arm128_prerender"):
        setup = frame.window_setup(params, CHAINS["left_arm"].segments[:2], ARM_WINDOW, case.endswith("prerender"))
        return replace(setup, moving=CHAINS["left_arm"].segments)
    if case == "head64_prerender":
        return frame.window_setup(params, CHAINS["head"].segments, SMALL_WINDOW, True)
    raise ValueError(case)


def _rate(energy, params: np.ndarray, batch: int, seconds: float) -> float:
    rng = np.random.default_rng(1)
    cands = np.repeat(params[None], batch, axis=0)
    cands[:, 6:] += rng.normal(0.0, 0.02, (batch, 29))
    energy(cands)  # warm up (GL programs, caches)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        energy(cands)
        n += batch
    return n / (time.perf_counter() - t0)


def _worker_rate(args) -> float:
    backend, case, batch, seconds, seed = args
    model = load_body_model()
    frame, params = make_frame(model, seed)
    return _rate(make_energy(backend, model, energy_setup(case, frame, params)), params, batch, seconds)


def make_frame(model, seed: int = 0):
    """A synthetic 8-camera 320x240 frame: the skinned body rendered at a random pose, perturbed start."""
    from common.body import forward_kinematics, skinned_vertices
    from common.camera import circle_studio
    from common.render_gl import MeshRenderer

    rng = np.random.default_rng(seed)
    studio = circle_studio(8, 320, 240)
    truth = _bench_pose(model, rng)
    masks = np.stack(MeshRenderer(studio, model.triangles).render_masks(
        skinned_vertices(model, forward_kinematics(model, truth))))
    start = truth.copy()
    start[6:] += rng.normal(0.0, 0.05, 29)
    return FrameData(model, studio, masks), start


def energy_rows(backends=("cpu", "gl"), cases=tuple(PAPER_TABLE1), seconds: float = MEASURE_SECONDS,
                processes: int = 2) -> list[dict]:
    """Evaluations/s per backend and case: one process, batched, and `processes` in parallel."""
    model = load_body_model()
    frame, params = make_frame(model)
    rows = []
    for backend in backends:
        for case in cases:
            try:
                energy = make_energy(backend, model, energy_setup(case, frame, params))
            except Exception as exc:  # a backend that cannot run here (no EGL) is reported, not fatal
                rows.append({"backend": backend, "case": case, "error": str(exc)})
                continue
            single = _rate(energy, params, 1, seconds)
            batched = _rate(energy, params, BATCH, seconds)
            parallel = None
            if processes > 1 and backend == "cpu":
                with mp.get_context("spawn").Pool(processes) as pool:
                    parallel = float(sum(pool.map(_worker_rate, [(backend, case, BATCH, seconds, 0)] * processes)))
            rows.append({
                "backend": backend, "case": case,
                "evals_per_second": float(parallel if parallel is not None else batched),
                "evals_per_second_one_core_batched": float(batched),
                "evals_per_second_one_core_single": float(single),
                "processes": processes if parallel is not None else 1,
                "batch": BATCH,
                "paper_evals_per_second": PAPER_TABLE1[case],
            })
    return rows


def fit_rows(sequence: Path, frames: int) -> list[dict]:
    """Seconds per frame fitting a sequence, single process. Tracking (the paper's measure): the
    default (the start, its turns either way and a tilted start fitted, the best polished and its
    limbs re-detected), without pre-rendering, without the turns, without the polishing rounds; then the default's tracking and refinement pass together, from the same run.
    Only the default run refines; the others time tracking alone."""
    from common.sequence import load_sequence
    from server.session import LocalSolver, run_fit

    model = load_body_model()
    seq = load_sequence(sequence)
    rows = []
    tracking = FitOptions(refine_passes=0)
    for label, options, paper in (("single_xorpr", FitOptions(), PAPER_TABLE2["single_xorpr"]),
                                  ("single_xor", replace(tracking, prerender=False), PAPER_TABLE2["single_xor"]),
                                  ("single_xorpr_no_turn_hypotheses", replace(tracking, turn_hypotheses=0), None),
                                  ("single_xorpr_no_polish", replace(tracking, polish_iterations=0), None)):
        with tempfile.TemporaryDirectory(prefix=f"mocap-bench-{label}-") as out:
            summary = run_fit(model, seq, Path(out), options, LocalSolver(model, options), max_frames=frames)
        row = {"mode": label, "energy_backend": "cpu", "seconds_per_frame": summary["seconds_per_frame"],
               "paper_seconds_per_frame": paper, "frames": summary["frames"],
               "mean_joint_error_mm": summary.get("tracking_mean_joint_error_mm")}
        rows.append(row)
        if options.refine_passes:
            rows.append({**row, "mode": f"{label}_refined",
                         "seconds_per_frame": summary["seconds_per_frame"] + summary["refine_seconds_per_frame"]
                         + summary.get("finish_seconds_per_frame", 0.0),
                         "paper_seconds_per_frame": None, "mean_joint_error_mm": summary.get("mean_joint_error_mm")})
    return rows


def write_json(path: Path, rows) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rows, indent=1))


def print_energy_table(rows: list[dict]) -> None:
    print(f"{'backend':8} {'case':18} {'evals/s':>10} {'1 core':>10} {'unbatched':>10} {'paper':>8}")
    for r in rows:
        if "error" in r:
            print(f"{r['backend']:8} {r['case']:18} unavailable: {r['error']}")
            continue
        print(f"{r['backend']:8} {r['case']:18} {r['evals_per_second']:10.0f} "
              f"{r['evals_per_second_one_core_batched']:10.0f} {r['evals_per_second_one_core_single']:10.0f} "
              f"{r['paper_evals_per_second']:8.1f}")


ACCURACY_CLIPS = ("cmu_12_01_walk.bvh", "05_10.bvh", "06_08.bvh")  # walk, dance, basketball (bundled)
MAX_ERROR_TARGET_MM = 40.0  # issue 3: no joint further off in any frame


DRIFT_FRAMES = 20  # the "last 20 frames"; the drift check tracks them again after as many
# frames from a true start: tracking forgets a true start within about 7 frames (the walk, frames
# 80-86 tracked from frame 80's truth), so the last 20 of the 40 compare with the run's last 20
# as equals, whose only difference is how long a history each carries.


def restarted_tail_errors_mm(model, seq, workdir: Path, options: FitOptions, frames: int) -> np.ndarray:
    """(frames,) per-frame mean joint error (mm) of the sequence's last ``frames`` frames,
    tracked (no refinement) from the truth of the first of them, in a run of their own."""
    from server.session import LocalSolver, run_fit

    tail = copy.copy(seq)
    tail.frames = list(seq.frames[-frames:])
    tracking = replace(options, refine_passes=0, refine_search=False, refine_hops=0)
    summary = run_fit(model, tail, workdir, tracking, LocalSolver(model, tracking), init="truth",
                      overwrite=True)
    return np.asarray(summary["per_frame_error_mm"])


def accuracy_rows(frames: int, workdir: Path, clips=ACCURACY_CLIPS, options: FitOptions | None = None,
                  progress=None, restart: bool = True) -> list[dict]:
    """The issue-3 accuracy check: each clip at 30 fps in the 8-camera studio with Cheung noise,
    skinned surface, fitted single-process from the first frame's truth. Each row scores the
    run's result and, as ``tracking_*``, its frames as tracking left them (before refinement).

    With ``restart``, the last 2 x DRIFT_FRAMES frames are also tracked from the truth of the
    first of them (``restarted_tail_errors_mm``), and ``restart_last20_mean_mm`` is the mean of
    the last DRIFT_FRAMES. Drift is error that tracking carries along and adds up; a clip whose
    later frames are harder to track has a higher error there after a fresh start as well.
    ``drift_mm``, the tracking's last-20 error over the restarted one's, is what the whole
    run's history carried into those frames: near zero where nothing drifts, however hard the
    frames themselves are."""
    from common.camera import circle_studio
    from common.sequence import load_sequence
    from common.synth import SynthOptions, synthesize
    from server.session import LocalSolver, run_fit

    model = load_body_model()
    options = options or FitOptions()
    clip_dir = Path(__file__).resolve().parents[1] / "common" / "data" / "clips"
    rows = []
    for clip in clips:
        seq_dir = workdir / f"accuracy-{Path(clip).stem}"
        if not (seq_dir / "sequence.json").exists():  # the same sequences for every backend compared
            synthesize(model, circle_studio(), clip_dir / clip, seq_dir, SynthOptions(frames=frames, noise="cheung", seed=0))
        seq = load_sequence(seq_dir)
        summary = run_fit(model, seq, workdir / f"result-{Path(clip).stem}-{options.energy}", options,
                          LocalSolver(model, options), progress=progress, overwrite=True)
        row = {"clip": clip, "energy_backend": options.energy, "frames": summary["frames"],
               "refine_passes": options.refine_passes, "refine_search": options.refine_search,
               "refine_hops": options.refine_hops}
        for prefix in ("", "tracking_"):
            per_frame = summary[f"{prefix}per_frame_error_mm"]
            row.update({f"{prefix}mean_joint_error_mm": summary[f"{prefix}mean_joint_error_mm"],
                        f"{prefix}max_joint_error_mm": summary[f"{prefix}max_joint_error_mm"],
                        f"{prefix}first20_mean_mm": float(np.mean(per_frame[:20])),
                        f"{prefix}last20_mean_mm": float(np.mean(per_frame[-20:])),
                        # a max over target from one bad stretch or from many frames
                        f"{prefix}frames_over_max_target": sum(
                            v > MAX_ERROR_TARGET_MM for v in summary[f"{prefix}per_frame_max_error_mm"])})
        if restart and summary["frames"] >= 3 * DRIFT_FRAMES:  # the restart starts after the first 20
            restarted = restarted_tail_errors_mm(model, seq,
                                                 workdir / f"restart-{Path(clip).stem}-{options.energy}", options,
                                                 frames=2 * DRIFT_FRAMES)[-DRIFT_FRAMES:].mean()
            row.update({"restart_last20_mean_mm": float(restarted),
                        "drift_mm": row["tracking_last20_mean_mm"] - float(restarted)})
        rows.append({**row, "seconds_per_frame": summary["seconds_per_frame"],
                     "refine_seconds_per_frame": summary["refine_seconds_per_frame"],
                     "per_joint_error_mm": summary["per_joint_error_mm"]})
    return rows


INIT_TARGET_MM = 50.0  # issue 7: the first frame's mean joint error from automatic initialisation
TPOSE_FRAME = 0  # the CMU conversions' frame 0: an added T-pose
SHARED_CLIPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"  # ../shared beside the checkout


def shared_clips(root: Path | None = None) -> list[Path]:
    """The shared data's BVH clips (``root/*/*.bvh``, default SHARED_CLIPS), sorted; empty
    when it is missing."""
    root = SHARED_CLIPS if root is None else root
    return sorted(root.glob("*/*.bvh")) if root.is_dir() else []


def search_error_mm(model, record: dict, truth: dict) -> float:
    """Mean joint error (mm) of a record's forward fit: its "first_pass" where a backward
    refinement replaced it."""
    from common.scoring import joint_errors_mm

    params = record.get("first_pass", record)["params"]
    fitted = forward_kinematics(model, np.asarray(params)).joints[0]
    return float(joint_errors_mm(fitted, truth[record["frame"]]).mean())


def init_rows(clips: list[Path], frames: int, workdir: Path, seed: int = 0, tpose: bool = False,
              options: FitOptions | None = None, first_frame_only: bool = False, jobs: int = 1) -> list[dict]:
    """Automatic initialisation (issue 7): per clip, from frame 1 ("start", the first frame
    of motion), from a seeded random frame ("random") and, with ``tpose``, from frame 0
    ("tpose"), fit ``frames`` frames from the voxels (no truth) and from the truth.

    One row per clip and start: first_frame_error_mm (the voxel-started run's first frame)
    and whether it meets INIT_TARGET_MM, first_frame_seconds (initialisation and first fit),
    first_frame_evaluations, the two runs' mean joint errors and their difference (auto minus
    truth start), and the two runs' errors on their last frame, mm. A start whose automatic run
    fails (``UserError``: no actor in the voxels) gives a row with "error" and first_frame_ok
    false, and the benchmark goes on. With ``first_frame_only``, the sequences and starts are
    the same (the random frames and the actor's place in the studio depend on ``frames``), but
    each run fits its first frame alone: the search, without the backward refinement. The
    starts are drawn first, in clip order, so ``jobs`` processes (one start each at a time, one
    core each) give the rows one process gives.
    """
    from common.bvh import read_bvh

    options = options or FitOptions()
    rng = np.random.default_rng(seed)
    plan = []
    for clip in clips:
        total = read_bvh(clip).num_frames
        starts = [("start", 1), ("random", int(rng.integers(1, max(2, total - 4 * frames))))]
        if tpose:
            starts.append(("tpose", TPOSE_FRAME))
        plan += [(clip, label, start, frames, workdir, seed, options, first_frame_only) for label, start in starts]
    if jobs <= 1:
        return [_init_row(*p) for p in plan]
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(jobs) as pool:
        return list(pool.map(_init_row, *zip(*plan)))


def _init_row(clip: Path, label: str, start: int, frames: int, workdir: Path, seed: int, options: FitOptions,
              first_frame_only: bool) -> dict:
    """One row of ``init_rows``."""
    from common.camera import circle_studio
    from common.sequence import load_sequence
    from common.synth import SynthOptions, synthesize
    from server.results import load_records
    from server.session import LocalSolver, run_fit

    model = load_body_model()
    fitted = 1 if first_frame_only else None
    seq_dir = workdir / f"init-{clip.stem}-{label}"
    synthesize(model, circle_studio(), clip, seq_dir, SynthOptions(frames=frames, start=start, noise="cheung", seed=seed))
    seq = load_sequence(seq_dir)
    auto_dir = workdir / f"auto-{clip.stem}-{label}"
    try:
        auto = run_fit(model, seq, auto_dir, options, LocalSolver(model, options), init="auto",
                       max_frames=fitted, overwrite=True)
    except UserError as exc:  # the clip's other rows still count (an actor out of most views)
        return {"clip": clip.name, "start": label, "start_frame": start, "first_frame_ok": False, "error": str(exc)}
    given = run_fit(model, seq, workdir / f"truth-{clip.stem}-{label}", options, LocalSolver(model, options),
                    init="truth", max_frames=fitted, overwrite=True)
    first = auto["per_frame_error_mm"][0]
    first_record = load_records(auto_dir)[0]
    return {"clip": clip.name, "start": label, "start_frame": start, "frames": auto["frames"],
            "refine_search": options.refine_search, "refine_hops": options.refine_hops,
            "first_frame_error_mm": first, "first_frame_ok": bool(first <= INIT_TARGET_MM),
            # the search's own first frame, before the backward refinement replaced it
            "first_frame_search_error_mm": search_error_mm(model, first_record, seq.truth()),
            "first_frame_seconds": first_record["seconds"], "first_frame_evaluations": first_record["evaluations"],
            "auto_mean_joint_error_mm": auto["mean_joint_error_mm"],
            "truth_start_mean_joint_error_mm": given["mean_joint_error_mm"],
            "auto_minus_truth_start_mm": auto["mean_joint_error_mm"] - given["mean_joint_error_mm"],
            # whether tracking forgets how it started: the runs' last frames
            "auto_last_frame_error_mm": auto["per_frame_error_mm"][-1],
            "truth_start_last_frame_error_mm": given["per_frame_error_mm"][-1]}


def print_init_table(rows: list[dict]) -> None:
    """The init rows as a table on stdout, then how many first frames meet the target."""
    print(f"{'clip':28s} {'start':>6s} {'frame':>6s} {'search mm':>9s} {'first mm':>9s} {'auto mm':>8s} {'truth mm':>9s} "
          f"{'last auto':>9s} {'last truth':>10s} {'s':>5s}")
    for r in rows:
        if "error" in r:
            print(f"{r['clip']:28s} {r['start']:>6s} {r['start_frame']:6d} failed: {r['error']}")
            continue
        print(f"{r['clip']:28s} {r['start']:>6s} {r['start_frame']:6d} {r['first_frame_search_error_mm']:9.1f} "
              f"{r['first_frame_error_mm']:9.1f} "
              f"{r['auto_mean_joint_error_mm']:8.1f} {r['truth_start_mean_joint_error_mm']:9.1f} "
              f"{r['auto_last_frame_error_mm']:9.1f} {r['truth_start_last_frame_error_mm']:10.1f} "
              f"{r['first_frame_seconds']:5.1f}")
    ok = sum(r["first_frame_ok"] for r in rows)
    print(f"first frame <= {INIT_TARGET_MM:.0f} mm: {ok} of {len(rows)}")


def preset_rows(seq: Path, frames: int, workdir: Path, presets=None) -> list[dict]:
    """``mocap fit --preset P --init auto`` for each preset on the same frames: wall seconds per
    frame with everything a user waits for (the actor-size search, the first frame's search from
    the voxels, tracking, the refinement), each part's share, and the joint error, from one run
    each, on every core (``mocap fit``'s default threads)."""
    from server.cli import main as mocap
    from server.config import PRESETS
    from server.results import load_records

    rows = []
    for name in presets or PRESETS:
        out = workdir / f"preset-{name}"
        code = mocap(["fit", str(seq), "--out", str(out), "--preset", name, "--frames", str(frames), "--init", "auto",
                      "--quiet", "--overwrite"])
        if code:
            raise UserError(f"bench presets: mocap fit --preset {name} failed ({code})")
        summary = json.loads((out / "summary.json").read_text())
        records = load_records(out)
        rows.append({"preset": name, "frames": summary["frames"], "init": summary["init"],
                     "threads": summary["threads"],
                     "wall_seconds_per_frame": summary["wall_seconds"] / summary["frames"],
                     "actor_size_seconds": summary["actor_size_seconds"],
                     "first_frame_seconds": records[0]["seconds"],
                     "tracking_seconds_per_frame": float(np.mean([r["seconds"] for r in records[1:]] or [0.0])),
                     "refine_seconds_per_frame": summary["refine_seconds_per_frame"],
                     "mean_joint_error_mm": summary.get("mean_joint_error_mm"),
                     "max_joint_error_mm": summary.get("max_joint_error_mm"),
                     "options": summary["options"]})
    return rows
