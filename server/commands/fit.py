"""mocap fit: fit the body model to every frame of a sequence (single process or with clients)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from common.body import load_body_model
from common.errors import UserError, print_warning
from common.export import sample_rate, write_motion_bvh
from common.fitting import ENERGY_BACKENDS, FitOptions
from common.schedule_tables import check_first_starts, schedules_from_table
from common.search import SCHEDULES, Schedules
from common.sequence import MAX_MASK_THRESHOLD, load_sequence
from common.world import UP_CHOICES
from common.argtypes import count
from server.local_cluster import LocalCluster, add_cluster_arguments, terminate_on_sigterm
from server.config import MAX_ACTOR_HEIGHT, MIN_ACTOR_HEIGHT, PRESETS, SEARCH_KNOBS, setting_default
from server.progress import Progress
from server.output import (add_calibration_argument, add_overwrite_argument, add_units_argument, check_folder_target,
                           counted, next_steps, replace_file, shell_word)
from server.results import DERIVED_FILES, MOTION_FILE, RESULT_FILES, earlier_actor_scale, load_records
from server.session import (ACTOR_SCALES, LocalSolver, choose_actor_scale, refinement_note, run_fit,
                            masks_cleared_note, tracking_error_note, usable_cameras, xor_sides)
from server.threads import resolve_threads

INIT_CHOICES = ("auto", "truth", "standing")


def add_fit_arguments(p) -> None:
    p.add_argument("sequence", type=Path, help="sequence folder (calibration.json + silhouettes/)")
    p.add_argument("--config", type=Path, default=None, metavar="Config.toml",
                   help="defaults from this file's [fit] and [calibration] sections (see mocap config keys); "
                        "options given here win")
    p.add_argument("--preset", choices=tuple(PRESETS), default=None,
                   help="fast (online: the previous pose and that pose moved on as it moved, no turns, no refinement), "
                        "default, or best (offline: two refinement passes with limb search and 60 hops); over the "
                        "--config file's [fit] preset, under its other keys and the options given")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="a Config.toml key for this run, over --config's and the preset's (e.g. fit.grid_steps=7, "
                        "fit.redetect=false; mocap config keys lists them): the search's own knobs have no option "
                        "of their own")
    p.set_defaults(command_parser=p)  # server.cli re-parses with the preset's and file's values as defaults
    # the search's knobs, which only a Config.toml or --set changes, at their settings' defaults
    p.set_defaults(**{key: setting_default("fit", key) for key in SEARCH_KNOBS})
    p.add_argument("--out", type=Path, required=True, help="result folder")
    p.add_argument("--energy", choices=ENERGY_BACKENDS, default="cpu", help="energy backend (default cpu)")
    p.add_argument("--frames", type=count(1), default=None, help="fit only the first N frames")
    p.add_argument("--iterations", type=count(1), default=FitOptions.max_iterations,
                   help=f"rounds per frame (default {FitOptions.max_iterations})")
    p.add_argument("--turn-hypotheses", type=count(0), default=FitOptions.turn_hypotheses, metavar="N",
                   help="also fit each frame from the start turned by -+1..N turn steps about the vertical and "
                        f"keep the lowest energy (default {FitOptions.turn_hypotheses}; 0: off, a fifth of the time)")
    p.add_argument("--track-moved-on", action=argparse.BooleanOptionalAction, default=FitOptions.track_moved_on,
                   help="tracking also fits each frame from the previous pose moved on by as much as it moved since "
                        "the frame before (on in the fast preset: a start where the actor keeps going)")
    p.add_argument("--polish-iterations", type=count(0), default=FitOptions.polish_iterations, metavar="N",
                   help="then up to N more rounds for the best of them while the energy still falls "
                        f"(default {FitOptions.polish_iterations}; 0: off)")
    p.add_argument("--refine-passes", type=count(0), default=FitOptions.refine_passes, metavar="N",
                   help="after tracking, fit every frame again N times, backwards then forwards alternately, each "
                        f"from its neighbour's fit, keeping the lower energy (default {FitOptions.refine_passes}; "
                        "0: tracking only, under half the time)")
    p.add_argument("--refine-search", action="store_true",
                   help="the first refinement pass also fits every frame from each limb's other basins, as a "
                        "first frame is: about three times tracking's time (offline work)")
    p.add_argument("--refine-hops", type=count(0), default=FitOptions.refine_hops, metavar="N",
                   help="the first refinement pass also fits every frame by N hops: one chain moved at random, "
                        "then the whole body fitted at once, the lowest energy kept (basin hopping; 60: about a "
                        "dozen times tracking's time, offline work; default 0)")
    p.add_argument("--refine-chunk-frames", type=count(0), default=FitOptions.refine_chunk_frames, metavar="N",
                   help="refine a long take in chunks of about N frames side by side on the threads, meeting "
                        "where they join (default 0: the take as one)")
    p.add_argument("--init", choices=INIT_CHOICES, default=None,
                   help="first-frame start: auto (from the voxels; the truth then only scores), truth, or "
                        "standing (default: the truth's first pose if the sequence has one, else auto)")
    add_units_argument(p)
    add_world_arguments(p)
    p.add_argument("--actor-height", default="auto", metavar="M|auto",
                   help="the actor's height in metres, in the fit's world (the calibration after --units): the body "
                        "model is scaled to it; "
                        "auto (default): the model's own size when starting from the truth, else chosen by the "
                        f"first frame's silhouettes among {ACTOR_SCALES[0]:g}-{ACTOR_SCALES[-1]:g} times the model's "
                        "1.67 m (printed with the result: a size far from 1 can mean a calibration in other units)")
    p.add_argument("--resume", action="store_true",
                   help="continue a result folder after a crash (with the options it was started with)")
    add_overwrite_argument(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar, no table")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def options_from_args(args) -> FitOptions:
    try:
        return FitOptions(energy=args.energy, max_iterations=args.iterations, grid_steps=args.grid_steps,
                          grid_range_rad=args.grid_range, prerender=args.prerender,
                          turn_hypotheses=args.turn_hypotheses, track_moved_on=args.track_moved_on,
                          turn_step_rad=args.turn_step, polish_iterations=args.polish_iterations,
                          refine_passes=args.refine_passes, refine_search=args.refine_search,
                          refine_hops=args.refine_hops, refine_chunk_frames=args.refine_chunk_frames,
                          spine_twist_prior=args.spine_twist_prior,
                          redetect_limbs=args.redetect)
    except ValueError as exc:  # a value out of range: say which option
        raise UserError(f"bad fit option: {exc}") from None


def schedules_from_args(args, options: FitOptions) -> Schedules:
    """The schedules of a Config.toml's ``[fit.schedules]`` (``--config``, ``--set``) over the
    defaults (checked as the file was read), each able to start under ``options``."""
    try:
        schedules = schedules_from_table(args.schedules)
        check_first_starts(schedules, options)
    except ValueError as exc:
        raise UserError(f"[fit.schedules] {exc}") from None
    return schedules


def finish(model, seq, args, summary: dict) -> None:
    """Files made from the results: the BVH (a finished run's only where a stop before it left
    none), and the summary on the terminal; a warning where a resumed run leaves reports and
    exports of the result before it."""
    complete = bool(summary.get("already_complete"))
    if complete:
        print_warning(f"{args.out}: already complete ({counted(summary['frames'], 'frame')}); nothing to resume "
                      "(--overwrite fits it again)")
    records = load_records(args.out)
    stale = [name for name in DERIVED_FILES if (args.out / name).exists()]
    if args.resume and not complete and stale:  # the new frames, and refinement over the old ones
        print_warning(f"{args.out}: {', '.join(stale)} {'was' if len(stale) == 1 else 'were'} made from the result "
                      "before this run went on; "
                      "make them again (mocap report, mocap export --overwrite)")
    if records and not (complete and (args.out / MOTION_FILE).is_file()):
        import numpy as np

        params = np.array([r["params"] for r in records])
        rate = sample_rate(np.array([r["frame"] for r in records]), seq.fps)
        replace_file(args.out / MOTION_FILE, lambda tmp: write_motion_bvh(tmp, model, params, rate))
    if args.json:
        print(json.dumps(summary, indent=1))
    elif not args.quiet:
        print_summary(summary, sys.stdout, args.out)
        result = shell_word(args.out)
        print(next_steps(f"mocap report {result}", f"mocap export {result} --format all "
                                                   f"({args.out / MOTION_FILE} is written already)"))


def print_summary(summary: dict, out, result: Path | None = None) -> None:
    """The summary table of a fit; ``result``: its folder, for the commands the table names."""
    rows = [("frames", summary["frames"]), ("mode", f"{summary['mode']} ({counted(summary['clients'], 'client')}"
                     + (f", {summary['threads']} threads)" if summary.get("threads", 1) > 1 else ")")),
            ("energy", summary["energy_backend"]),
            ("world up", summary.get("world_up", "+z")),
            ("actor size", f"{summary.get('actor_scale', 1.0):.2f} x the body model"
                           + (" (chosen from the first frame; --actor-height sets it)"
                              if summary.get("actor_size_seconds") else "")),
            ("wall time", wall_time_note(summary)),
            ("tracking s/frame (median)", f"{summary['seconds_per_frame']:.3f}" if summary["seconds_per_frame"] else "-"),
            ("evaluations/frame", f"{summary['evaluations_per_frame']:.0f}" if summary["evaluations_per_frame"] else "-")]
    refined = bool(summary.get("refinement_passes"))
    if refined:
        rows.append(("refinement s/frame", f"{summary['refine_seconds_per_frame']:.3f} {refinement_note(summary)}"))
        if summary.get("finish_seconds_per_frame"):
            rows.append(("finish s/frame", f"{summary['finish_seconds_per_frame']:.3f} "
                                           f"({counted(summary['frames_finished'], 'frame')} lowered)"))
    if "mean_joint_error_mm" in summary:
        tracked = f" (tracking alone {tracking_error_note(summary)})" if refined else ""
        rows += [("mean / max joint error", f"{summary['mean_joint_error_mm']:.1f} / "
                                            f"{summary['max_joint_error_mm']:.1f} mm{tracked}")]
    quality = summary.get("fit_quality")
    if quality:  # without truth the only check of a take: how much of the silhouettes the body explains
        flagged = len(quality.get("frames_flagged", []))
        rows.append(("XOR / silhouette area", f"{quality['mean_xor_share']:.0%} mean, {quality['max_xor_share']:.0%} "
                                              f"worst; {flagged} of {counted(summary['frames'], 'frame')} over "
                                              f"{quality['flag_share']:.0%} in a camera (mocap report "
                                              f"{shell_word(result) if result else 'RESULT'} names them)"))
        if "mean_missed_share" in quality:
            rows.append(("of which", xor_sides(quality)))
    if left_out := summary.get("foreground_left_out"):
        rows.append(("masks cleared", masks_cleared_note(left_out)))
    rows += _cluster_rows(summary)
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"  {k.ljust(width)}  {v}", file=out)


def wall_time_note(summary: dict) -> str:
    """'24.4 s, 1.11 s a frame (the actor-size search 4.2 s)': everything a user waited for, where
    a take's median frame leaves out the size search, the first frame's search and refinement."""
    wall, frames = summary.get("wall_seconds"), summary.get("frames_fitted_this_run") or summary.get("frames")
    if not wall or not frames:
        return "-"
    size = summary.get("actor_size_seconds")
    return f"{wall:.1f} s, {wall / frames:.2f} s a frame" + (f" (the actor-size search {size:.1f} s)" if size else "")


def _cluster_rows(summary: dict) -> list:
    """Compute / waiting / transfer per process (s/frame), the server's rounds against their jobs'
    CPU, and the failure counters of a cluster run."""
    timing, frames = summary.get("timing", {}), max(summary.get("frames_fitted_this_run") or 0, 1)
    rows = []
    for p in timing.get("processes", []):
        split = " / ".join(f"{p[k] / frames:.3f}" for k in ("compute_seconds", "waiting_seconds", "transfer_seconds"))
        rows.append((f"{p['name']} compute/wait/transfer", f"{split} s/frame, {p['chains']} chains"))
        if p.get("rounds"):
            rows.append(("rounds", f"{p['rounds'] / frames:.1f} a frame, {p['round_seconds'] / frames:.3f} s for "
                                   f"{p['round_job_cpu_seconds'] / frames:.3f} s of their jobs' CPU; the server "
                                   f"alone between them {p['between_rounds_seconds'] / frames:.3f} s/frame, "
                                   f"{p.get('short_rounds', 0) / frames:.1f} rounds of short jobs kept"))
    if "dropped" in timing:
        dropped = sum(timing["dropped"].values())
        rows.append(("dropped / resent / lost", f"{dropped} messages / {timing['resent']} chains / "
                                                f"{counted(timing['lost_clients'], 'client')}"))
    return rows


def register(sub) -> None:
    p = sub.add_parser("fit", help="fit the body model to a sequence")
    add_fit_arguments(p)
    p.add_argument("--threads", type=count(0), default=0,
                   help="fit this many starts and limbs at once (default 0: every core, or $MOCAP_THREADS); with "
                        "--clients, the server's threads for the rounds it keeps; the poses are the same for any number")
    p.add_argument("--clients", type=count(0), default=0,
                   help="start N local limb clients and a server on 127.0.0.1 (default 0: one process)")
    add_cluster_arguments(p, server=False)
    p.set_defaults(func=run)


def add_world_arguments(p, clean: bool = True) -> None:
    """--up, --calibration and --mask-threshold: how a sequence's world and masks are read (fit,
    voxels, live, server, sync); with ``clean`` also --no-clean-masks."""
    p.add_argument("--up", choices=UP_CHOICES, default="auto",
                   help="the calibration world's up axis (default auto: from the cameras, which stand above "
                        "the floor); fitting runs z up, results are written in the calibration's frame")
    add_calibration_argument(p)
    p.add_argument("--mask-threshold", type=count(0, MAX_MASK_THRESHOLD - 1), default=None, metavar="N",
                   help="accept grey or colour images as silhouettes: pixels brighter than N are foreground "
                        "(8-bit images: 0-254; 16-bit: up to 65534; 1-bit masks need none)")
    if clean:
        p.add_argument("--no-clean-masks", dest="clean_masks", action="store_false",
                       help="fit the masks as they are (default: blobs the other cameras do not support are dropped)")


def actor_model(model, seq, options, args, init: str, threads: int = 0, schedules: Schedules = SCHEDULES):
    """(the body model at the actor's size, the ``ActorSize`` search that chose it or None)
    (``--actor-height``; auto: see ``choose_actor_scale``, on ``threads`` threads, 0: as
    ``resolve_threads`` says; the search by ``schedules``' wide one)."""
    if args.actor_height != "auto":
        try:
            height = float(args.actor_height)
        except ValueError:
            raise UserError(f"--actor-height: expected metres or auto, got {args.actor_height!r}") from None
        if not MIN_ACTOR_HEIGHT <= height <= MAX_ACTOR_HEIGHT:
            raise UserError(f"--actor-height: expected {MIN_ACTOR_HEIGHT:g} to {MAX_ACTOR_HEIGHT:g} metres, "
                            f"got {height}")
        return model.scaled(height / model.height), None
    scale = earlier_actor_scale(args.out) if args.resume else None
    if scale is not None:  # the size the run being continued chose
        return (model.scaled(scale) if scale != 1.0 else model), None
    if init == "truth":
        return model, None
    size = choose_actor_scale(model, seq, options, resolve_threads(threads, options), schedules)
    if size.scale in (ACTOR_SCALES[0], ACTOR_SCALES[-1]):
        edge, beyond = ("largest", "larger") if size.scale == ACTOR_SCALES[-1] else ("smallest", "smaller")
        print_warning(f"actor size {size.scale:.2f} is the {edge} the size search tries ({ACTOR_SCALES[0]:g}-"
                      f"{ACTOR_SCALES[-1]:g} times the body model): the actor may be {beyond} still, the masks "
                      "may hold more or less than the actor (a prop sat on, shadows, parts missing), or the "
                      "calibration's scale may be off (mocap calib show prints the cameras' heights); "
                      "--actor-height sets the size")
    return (model.scaled(size.scale) if size.scale != 1.0 else model), size


def warn_if_software_gl(energy: str) -> None:
    """``--energy gl`` where OpenGL is a software renderer (Mesa llvmpipe): the paper's method
    runs, but over a thousand times slower than ``--energy cpu`` (`mocap bench energy`)."""
    if energy != "gl":
        return
    from common.render_gl import gl_renderer_name, is_software_renderer

    if is_software_renderer():
        print_warning(f"--energy gl: OpenGL here is {gl_renderer_name()}, a software renderer: tens of whole-body "
                      "evaluations a second against tens of thousands for --energy cpu (the ellipsoids, the fast "
                      "path), so each frame takes many minutes")


def check_resume_or_overwrite(args) -> None:
    if args.resume and args.overwrite:
        raise UserError("--resume continues the result there and --overwrite replaces it: give one of them")


def open_sequence_to_fit(args):
    """The sequence ``mocap fit`` or ``mocap server`` fits, its masks checked for the frames to
    fit before the actor-size search reads them, without the cameras whose masks tell nothing
    (``usable_cameras``); a result folder that is the sequence's is refused."""
    seq = load_sequence(args.sequence, args.units, up=args.up, mask_threshold=args.mask_threshold,
                        clean_masks=args.clean_masks, calibration=args.calibration)
    if Path(args.out).resolve() == seq.path.resolve():
        raise UserError(f"--out {args.out}: the sequence folder itself; choose a folder of its own for the result")
    if args.frames and args.frames > len(seq.frames):
        print_warning(f"--frames {args.frames}: {seq.path} has {counted(len(seq.frames), 'frame')}; fitting them all")
    return usable_cameras(seq, seq.frames[:args.frames] if args.frames else seq.frames)


def run(args) -> int:
    check_resume_or_overwrite(args)
    # the folder first: a result in the way is refused before the slow actor-size search
    check_folder_target(args.out, RESULT_FILES, resume=args.resume, overwrite=args.overwrite)
    warn_if_software_gl(args.energy)
    base = load_body_model()
    seq = open_sequence_to_fit(args)
    options = options_from_args(args)
    schedules = schedules_from_args(args, options)
    init = args.init or ("truth" if seq.truth() else "auto")
    model, size = actor_model(base, seq, options, args, init, args.threads, schedules)
    total = min(len(seq.frames), args.frames or len(seq.frames))
    bar = Progress("fit", total, enabled=None if not args.quiet else False)
    if args.clients == 0:
        # SIGTERM (a job scheduler's stop) unwinds like Ctrl-C: the run says what it kept
        solver = LocalSolver(model, options, resolve_threads(args.threads, options))
        try:
            with terminate_on_sigterm():
                summary = run_fit(model, seq, args.out, options, solver, init=args.init, resume=args.resume,
                                  max_frames=args.frames, progress=bar, overwrite=args.overwrite, actor_size=size,
                                  schedules=schedules)
        finally:
            solver.close()
    else:
        # SIGTERM unwinds like Ctrl-C, so the local clients are stopped either way
        with terminate_on_sigterm(), LocalCluster(options, args.clients, heartbeat_interval=args.heartbeat,
                                                  client_timeout=args.client_timeout, threads=args.threads) as solver:
            summary = run_fit(model, seq, args.out, options, solver, init=args.init, resume=args.resume,
                              max_frames=args.frames, progress=bar, overwrite=args.overwrite, actor_size=size,
                              schedules=schedules)
    finish(model, seq, args, summary)
    return 0
