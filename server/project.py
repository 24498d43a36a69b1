"""``mocap run``: every step from a take's raw files to its report.

A take's layouts, recordings and calibration: ``server.takes``.

Steps (import, segment, fit, export, report) run the ``mocap`` commands themselves, so every
check and message is theirs. Each step leaves a record (``TAKE/.mocap/<step>.json``) of its
settings and of the sizes and times of its inputs and outputs; a step whose settings and
inputs match its record, and whose outputs are all there, is done and skipped, so a run after a
change redoes only what the change affects. Outputs edited by hand since (silhouettes touched
up, a calibration.json corrected) are kept as edited (the step's status is "kept (edited)")
and the steps that read them run again, as make does; an output removed makes its step run.
A run replaces only outputs that a run made and that are as it left them (``made.json``; an
output kept as edited is not vouched for): any other output in the way of a step that runs
(made by hand, or changed since) refuses the take before anything is written, unless
``overwrite``. A step being run leaves ``<step>.pending.json`` until it is done, so what it
was replacing when stopped is still its own. A fit that was interrupted is continued
(``--resume``); one whose settings changed is replaced. A lock file keeps two runs off one take.

One module of about 670 lines: a take's plan, its steps' records and the run are read
together (which steps run follows from the records of the plan's inputs and outputs, and the
records from what the run did).
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

from common.calibration import calibration_files, camera_files_in, camera_files_named
from common.errors import WARNING_PREFIX, UserError
from common.export import export_name, named_formats
from server.config import OPTION_KEYS, RECORDED_WHEN_SET, SEARCH_KNOBS, Config, setting_default, toml_value
from server.output import counted, write_text
from server.results import DERIVED_FILES, FOREGROUND_FILE, MOTION_FILE, RUN_FILE
from server.takes import (SOURCE_FOLDERS, TAKE_LAYOUTS, camera_folder_sources, find_calibration, holds_calibration,
                          named_sources, shown_names, take_camera_files, take_config, takes_below, video_folders)

STATE_DIR = ".mocap"  # per take: step records, the lock, the log of the last run
MADE_FILE = "made.json"  # in STATE_DIR: every output a run made, as it left it
STEPS = ("import", "segment", "fit", "export", "report")


def _files(root: Path) -> list[Path]:
    return [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file()) if root.exists() else []


def _hash_files(h, root: Path, files: list[Path]) -> None:
    for p in files:
        st = p.stat()
        h.update(f"{p.relative_to(root) if p != root else ''}:{st.st_size}:{st.st_mtime_ns}\n".encode())


def fingerprint(paths: list[Path]) -> str:
    """A hash of the names, sizes and modification times of every file under ``paths``."""
    h = hashlib.sha1()
    for root in paths:
        files = _files(root)
        h.update(f"{root}:{len(files)}\n".encode())
        _hash_files(h, root, files)
    return h.hexdigest()


def _as_left(path: Path) -> str:
    """A hash of the sizes and modification times of the files under one output, by their names
    below it: the same after the take is moved."""
    h = hashlib.sha1()
    _hash_files(h, path, _files(path))
    return h.hexdigest()


def _relative(take: Path, path: Path) -> str:
    return os.path.relpath(path, take)


@dataclass(frozen=True)
class Step:
    """One step of a take: the mocap command lines, what it reads and writes, what decides it.

    ``also_writes``: what the commands write besides the outputs (noted in made.json like them,
    but not deciding whether the step is up to date); ``clears``: what the commands remove, which
    later steps make. All three are replaced only where a run made them.
    """

    name: str
    commands: tuple[tuple[str, ...], ...]
    inputs: tuple[Path, ...]
    outputs: tuple[Path, ...]
    settings: dict = field(default_factory=dict)
    also_writes: tuple[Path, ...] = ()
    clears: tuple[Path, ...] = ()

    @property
    def replaced(self) -> tuple[Path, ...]:
        """Everything the commands write or remove."""
        return self.outputs + self.also_writes + self.clears


@dataclass(frozen=True)
class TakePlan:
    """``recordings``: {take folder name: {camera: source}} of a take that is imported;
    ``calibration``: what it is imported with (in ``units``), or a ready sequence read with where
    it holds none of its own (None where it does)."""

    take: Path
    sequence: Path
    result: Path
    steps: tuple[Step, ...]
    recordings: dict[str, dict[str, Path]] = field(default_factory=dict)
    calibration: Path | None = None
    units: str = ""
    per_camera: bool = False  # laid out a folder per camera (``camera_folder_sources``)


def plan_take(take: Path, config: Config | None = None) -> TakePlan:
    """The steps of a take under its configuration (nothing is run or written).

    A folder with ``sequence.json`` is a ready sequence (one ``mocap import-video`` made, say):
    its images/ are its frames, not recordings to import again at a guessed frame rate. It is
    segmented only where it has images/ and no silhouettes/ (or silhouettes a run made), so that
    silhouettes made or touched up by hand are fitted as they are."""
    take = Path(take).resolve()
    if not take.is_dir():
        raise UserError(f"{take}: not a folder")
    config = config or take_config(take)
    result = take / config.get("take", "result")
    steps = []
    calib_settings = config.section("calibration")
    imports = {name: named_sources(take / name) for name in SOURCE_FOLDERS}
    source_kind = next((k for k, v in imports.items() if v), None)
    per_camera, per_camera_backgrounds = camera_folder_sources(take) if source_kind is None else ({}, {})
    if per_camera:  # a lab's own layout, imported as videos/ would be
        source_kind, imports["videos"] = "videos", per_camera
    recordings, calibration = {}, None
    calibration_file = None  # a ready sequence's: its own, or the take's or project's where it holds none
    if (take / "sequence.json").is_file() or ((take / "silhouettes").exists() and source_kind is None):
        sequence = take
        if not holds_calibration(take):
            calibration_file = find_calibration(take, config)
        if (take / "images").is_dir() and (not (take / "silhouettes").exists()
                                           or _read_record(take, "segment") is not None):
            # not the sequence's own sequence.json: segment adds its record there and keeps the rest
            steps.append(_segment_step(sequence, config, also_writes=(), calibration=calibration_file))
    elif source_kind is None:
        below = takes_below(take)  # a project's folder given for one of its takes
        partial = [f"{camera}/" for camera, named in video_folders(take).items() if not all(named.values())]
        raise UserError(f"{take}: not a take (no {TAKE_LAYOUTS})"
                        + (f"; it holds {counted(len(below), 'take')}: mocap batch {take} runs them all"
                           if below else "")
                        + (f"; {', '.join(partial)} hold video.<ext> but no background.<ext> (the empty studio)"
                           if partial else ""))
    else:
        sequence = take / config.get("take", "sequence")
        calibration = find_calibration(take, config, list(per_camera) if per_camera else None)
        videos = imports[source_kind]
        backgrounds = per_camera_backgrounds if per_camera else named_sources(take / "background")
        # segmentation subtracts the empty studio: a take without it is refused before the import
        recordings = {source_kind: videos, "background": backgrounds}
        imp = config.section("import")
        command = ["import-video", "--calibration", str(calibration), "--out", str(sequence), "--overwrite",
                   "--video", *[f"{cam}={path}" for cam, path in videos.items()],
                   "--start", str(imp["start"]), "--step", str(imp["step"])]
        command += ["--background", *[f"{cam}={path}" for cam, path in backgrounds.items()]]
        if imp["stop"]:
            command += ["--stop", str(imp["stop"])]
        if imp["fps"]:
            command += ["--fps", str(imp["fps"])]
        if imp["offsets"]:
            command += ["--offset", *[f"{cam}={n}" for cam, n in imp["offsets"].items()]]
        if imp["missing_frames"] != "error":
            command += ["--missing-frames", imp["missing_frames"]]
        if calib_settings["units"]:
            command += ["--units", calib_settings["units"]]
        # the files read, not a take read as its own calibration, which the run writes into
        inputs = (*calibration_files(calibration), *videos.values(), *backgrounds.values())
        steps.append(Step("import", (tuple(command),), inputs,
                          # not sequence.json: the segment step adds its record there
                          (sequence / "images", sequence / "calibration.json"),
                          {"import": imp, "calibration": calib_settings},
                          also_writes=(sequence / "background", sequence / "sequence.json"),
                          clears=(sequence / "silhouettes",)))  # import-video --overwrite drops the old ones
        steps.append(_segment_step(sequence, config, also_writes=(sequence / "sequence.json",)))
    fit = config.section("fit")
    command = ["fit", str(sequence), "--out", str(result), "--quiet", "--up", calib_settings["up"],
               "--iterations", str(fit["iterations"]), "--turn-hypotheses", str(fit["turn_hypotheses"]),
               "--polish-iterations", str(fit["polish_iterations"]), "--refine-passes", str(fit["refine_passes"]),
               "--refine-hops", str(fit["refine_hops"]), "--refine-chunk-frames", str(fit["refine_chunk_frames"]),
               "--energy", fit["energy"],
               "--actor-height", str(fit["actor_height"]), "--threads", str(fit["threads"])]
    command += ["--frames", str(fit["frames"])] if fit["frames"] else []
    # an imported sequence's calibration.json is in metres and says so: the units are the import's
    command += ["--units", calib_settings["units"]] if calib_settings["units"] and sequence == take else []
    command += ["--init", fit["init"]] if fit["init"] else []
    command += [] if fit["clean_masks"] else ["--no-clean-masks"]
    command += ["--refine-search"] if fit["refine_search"] else []
    command += ["--track-moved-on"] if fit["track_moved_on"] else []
    command += ["--mask-threshold", str(fit["mask_threshold"])] if fit["mask_threshold"] >= 0 else []
    for key in SEARCH_KNOBS:  # no option of their own: as a Config.toml's keys
        command += ["--set", f"fit.{key}={toml_value(fit[key])}"] if fit[key] != setting_default("fit", key) else []
    command += ["--calibration", str(calibration_file)] if calibration_file else []
    if calibration_file:
        calibration_read = calibration_files(calibration_file)
    elif sequence == take and not (take / "calibration.json").is_file():
        calibration_read = calibration_files(take)  # a ready sequence's own EasyMocap files
    else:
        calibration_read = [sequence / "calibration.json"]
    steps.append(Step("fit", (tuple(command),),
                      (*calibration_read, sequence / "silhouettes", sequence / "sequence.json"),
                      (result / "poses.jsonl", result / "summary.json"),
                      # the preset is in the keys it set, and its name alone refits nothing
                      {"fit": {k: v for k, v in fit.items() if k != "preset" and not (
                          k in RECORDED_WHEN_SET and v == setting_default("fit", k))}, "calibration": calib_settings},
                      also_writes=(result / RUN_FILE, result / MOTION_FILE, result / FOREGROUND_FILE),
                      # mocap fit --overwrite drops what was made from the result it replaces
                      clears=tuple(result / name for name in DERIVED_FILES)))
    formats = named_formats(config.get("export", "formats"))
    steps.append(Step("export", tuple(("export", str(result), "--format", f, "--overwrite", "--quiet") for f in formats),
                      (result / "poses.jsonl",), tuple(result / export_name(f) for f in formats),
                      {"formats": formats}))
    report = config.section("report")
    if report["enabled"]:
        command = ["report", str(result), "--overwrite", "--quiet"] + ([] if report["gif"] else ["--no-gif"])
        steps.append(Step("report", (tuple(command),), (result / "poses.jsonl", result / "summary.json"),
                          (result / "report.html",), {"report": report}, also_writes=(result / "pictures",)))
    return TakePlan(take, sequence, result, tuple(steps), recordings, calibration or calibration_file,
                    calib_settings["units"], bool(per_camera))


def plan_lines(plan: TakePlan) -> list[str]:
    """What ``mocap run`` would read and do for a take (``mocap config show``): its recordings'
    layout and cameras, the calibration read, the steps."""
    videos = next(iter(plan.recordings.values()), {})
    layout = ("a folder per camera" if plan.per_camera else f"{next(iter(plan.recordings))}/" if videos
              else "a ready sequence")
    calibration = str(plan.calibration) if plan.calibration else f"the sequence's own ({plan.sequence})"
    if plan.per_camera and plan.calibration == plan.take:
        files = [f for found in take_camera_files(plan.take, list(videos)) for f in found]  # one set: planned
        calibration = f"{camera_files_named(plan.take, files)} in {plan.take}"
    return [f"recordings: {layout}" + (f" ({', '.join(videos)})" if videos else ""),
            f"calibration: {calibration}" + (f" in {plan.units}" if plan.units else ""),
            f"steps: {', '.join(step.name for step in plan.steps)}; result: {plan.result}"]


def _segment_step(sequence: Path, config: Config, also_writes: tuple[Path, ...], calibration: Path | None = None) -> Step:
    """``also_writes``: the sequence.json that the segmentation's record goes into, where an import
    made it; ``calibration``: where the sequence holds none of its own."""
    given = ("--calibration", str(calibration)) if calibration else ()
    return Step("segment", (("segment", str(sequence), "--method", config.get("segmentation", "method"),
                             "--overwrite", *given),),
                (sequence / "images", sequence / "background",
                 *(calibration_files(calibration) if calibration else [])),
                (sequence / "silhouettes",), {"segmentation": config.section("segmentation")}, also_writes=also_writes)


def check_recordings(plan: TakePlan) -> None:
    """Raise UserError where an imported take's recordings do not match its calibration's
    cameras, naming the take's folder (import-video would name its options, which a user of
    mocap run never typed)."""
    if not plan.recordings:
        return
    from common.calibration import load_calibration

    # the calibration's warnings are the import's to say
    cameras = load_calibration(plan.calibration, units=plan.units or None, warn=lambda line: None).names
    for folder, given in plan.recordings.items():
        for camera, path in given.items():
            if camera not in cameras and plan.per_camera and plan.calibration == plan.take:
                at_top = camera_files_in(plan.take)  # cameras named by their files, not their folders
                raise UserError(f"{plan.take / camera}/: no calibration file " + (
                    f"{camera}.xml or .txt at the top of {plan.take} (cameras there: {', '.join(cameras)}; name each "
                    "file as its camera's folder)" if at_top else
                    f"beside its recording (.xml with K, R, t or P, .txt with a 3x4 P; cameras with one: "
                    f"{', '.join(cameras)})"))
            if camera not in cameras:
                raise UserError(f"{path}: no camera {camera} in {plan.calibration} (cameras: {', '.join(cameras)})")
        missing = [c for c in cameras if c not in given]
        if missing and plan.per_camera:  # name what a camera's folder must hold, and what it holds
            named = f"{'background' if folder == 'background' else 'video'}.<ext>"
            held = [f"{c}/ holds {', '.join(shown_names(plan.take / c)) or 'nothing'}"
                    for c in missing if (plan.take / c).is_dir()]
            raise UserError(f"{plan.take}: no {named} for camera(s) {', '.join(missing)} of {plan.calibration}"
                            + (f" ({'; '.join(held)})" if held else ""))
        if missing:
            what = "empty-studio recording" if folder == "background" else "recording"
            raise UserError(f"{plan.take / folder}/: no {what} for camera(s) {', '.join(missing)} of "
                            f"{plan.calibration}")
    for step in plan.steps:  # [import] offsets name cameras too
        unknown = [c for c in step.settings.get("import", {}).get("offsets", {}) if c not in cameras]
        if unknown:
            raise UserError(f"[import] offsets: no camera {', '.join(unknown)} in {plan.calibration} "
                            f"(cameras: {', '.join(cameras)})")


def _record_path(take: Path, step: str) -> Path:
    return take / STATE_DIR / f"{step}.json"


def _pending_path(take: Path, step: str) -> Path:
    return take / STATE_DIR / f"{step}.pending.json"


def _record(step: Step) -> dict:
    return {"settings": step.settings, "commands": [list(c) for c in step.commands],
            "inputs": fingerprint(list(step.inputs)), "outputs": fingerprint(list(step.outputs))}


def _pending(step: Step) -> dict:
    return {"settings": step.settings, "inputs": fingerprint(list(step.inputs))}


def _read_record(take: Path, step: str) -> dict | None:
    done = _read_json(_record_path(take, step))
    return done if isinstance(done, dict) else None


UP_TO_DATE = "up to date"
KEPT_EDITED = "kept (edited)"


def done_status(take: Path, step: Step) -> str | None:
    """Whether the step is done, as make says it: its record says its outputs were made from
    these settings and inputs, and they are all there. ``UP_TO_DATE`` where they are as it left
    them, ``KEPT_EDITED`` where they were edited since (kept, not made again: the steps that
    read them see that their inputs changed), None where the step must run."""
    done = _read_record(take, step.name)
    if done is None or not all(p.exists() for p in step.outputs):
        return None
    now = _record(step)
    if any(done.get(key) != now[key] for key in ("settings", "commands", "inputs")):
        return None
    return UP_TO_DATE if done.get("outputs") == now["outputs"] else KEPT_EDITED


def why_it_runs(take: Path, step: Step, inputs: str | None = None, resume: bool = False) -> str:
    """Why a step that is not done (``done_status`` None) runs, in a few words: never run;
    stopped before it finished (a fit then continues, ``resume``, unless its settings or inputs
    changed since); which settings changed (``[section] key old -> new``); its commands (a take
    moved: they hold its paths); its inputs (an earlier step made them again, or they were
    changed by hand); an output missing. ``inputs``: the inputs' fingerprint where the caller
    has it (else taken here). Read before the step's run touches its records; a record this
    version cannot read says so and never stops the run."""
    if resume:
        return "continued where it stopped"
    try:
        inputs = fingerprint(list(step.inputs)) if inputs is None else inputs
        done = _read_record(take, step.name)
        if done is None:
            pending = _read_json(_pending_path(take, step.name))
            if not isinstance(pending, dict):
                return "not run before"
            changed = _settings_changed(pending.get("settings"), step.settings)
            since = (f"; settings changed since: {changed}" if changed
                     else "; its inputs changed since" if pending.get("inputs") != inputs else "")
            return f"stopped before it finished{since}"
        if done.get("settings") != step.settings:
            return f"settings changed: {_settings_changed(done.get('settings'), step.settings) or 'as recorded'}"
        if done.get("commands") != [list(c) for c in step.commands]:
            return "its command changed"
        if done.get("inputs") != inputs:
            return "its inputs changed"
        missing = [p for p in step.outputs if not p.exists()]
        if missing:
            shown = _relative(take, missing[0]) if take in missing[0].parents else str(missing[0])
            return f"{shown} is missing"
    except (AttributeError, TypeError, ValueError):
        pass
    return "its record is out of date"


def _settings_changed(old, new: dict) -> str:
    """``[section] key old -> new`` for each setting of ``new`` (a step's settings: sections of
    keys, or keys) that differs from ``old`` (a record's), keys gone too; "" where none does."""
    def flat(settings) -> dict:
        out = {}
        for name, value in (settings.items() if isinstance(settings, dict) else ()):
            if isinstance(value, dict):
                out.update({f"[{name}] {key}": v for key, v in value.items()})
            else:
                out[name] = value
        return out
    before, after = flat(old), flat(new)
    return ", ".join(f"{key} {_shown(before.get(key, _UNSET))} -> {_shown(after.get(key, _UNSET))}"
                     for key in list(after) + [k for k in before if k not in after]
                     if before.get(key, _UNSET) != after.get(key, _UNSET))


_UNSET = object()  # a setting one of the two does not have


def _shown(value) -> str:
    return "(not set)" if value is _UNSET else json.dumps(value)


def _overlap(a: Path, b: Path) -> bool:
    return a == b or a in b.parents or b in a.parents


def steps_to_run(take: Path, plan: TakePlan) -> list[Step]:
    """The steps a run would run: those not done, and those after them that read or make what
    an earlier one that runs writes or removes (a fit after a new segmentation)."""
    running, replaced = [], []
    for step in plan.steps:
        if done_status(take, step) is None or any(_overlap(p, q) for p in step.inputs + step.outputs
                                                   for q in replaced):
            running.append(step)
            replaced += step.replaced
    return running


def edited_outputs(take: Path, plan: TakePlan, step: Step) -> list[str]:
    """The step's outputs (relative to the take) that are not as a run left them: those a step
    kept as edited names."""
    made = _made_by_runs(take, plan)
    names = [_relative(take, p) for p in step.outputs]
    return [n for n in names if made.get(n) != _as_left(take / n)] or names


def _made_by_runs(take: Path, plan: TakePlan) -> dict[str, str]:
    """{output relative to the take: its state as a run left it} (``made.json``, kept across steps
    and runs, so that a file one step wrote and another left alone, such as the fit's motion.bvh,
    stays vouched for). A take last run before made.json was kept: each step's record vouches
    for what it writes, whole."""
    made = _read_json(take / STATE_DIR / MADE_FILE)
    if isinstance(made, dict):
        return made
    return {_relative(take, p): _as_left(p) for step in plan.steps
            if (_read_record(take, step.name) or {}).get("outputs") == fingerprint(list(step.outputs))
            for p in step.outputs + step.also_writes if p.exists()}


def _note_made(take: Path, plan: TakePlan, step: Step) -> None:
    made = _made_by_runs(take, plan) | {_relative(take, p): _as_left(p) for p in step.outputs + step.also_writes
                                        if p.exists()}
    write_text(take / STATE_DIR / MADE_FILE, json.dumps(made, indent=1))


def _vouched_for(take: Path, plan: TakePlan) -> set[str]:
    """The outputs (relative to the take) that a run made and that are as it left them, or that a
    step it was running when it stopped was replacing."""
    vouched = {name for name, left in _made_by_runs(take, plan).items() if _as_left(take / name) == left}
    for step in plan.steps:
        if _pending_path(take, step.name).is_file():  # checked (or overwrite given) when it started
            vouched.update(_relative(take, p) for p in step.replaced)
    return vouched


def check_replaceable(take: Path, plan: TakePlan) -> None:
    """Raise UserError if a step that would run would replace or remove an output that a run did
    not make, or one changed since (a result made by hand, silhouettes touched up). A step that
    is done keeps its outputs, edited or not: it is not in the way."""
    vouched = _vouched_for(take, plan)
    for step in steps_to_run(take, plan):
        for path in step.replaced:
            name = _relative(take, path)
            if path.exists() and name not in vouched:
                raise UserError(f"{take}: {step.name}: {name} holds a result mocap run did not make (or one changed "
                                "since); move it away or pass --overwrite")


@contextlib.contextmanager
def take_lock(take: Path):
    """One run per take at a time (a second is refused); released when the process ends."""
    (take / STATE_DIR).mkdir(exist_ok=True)
    fh = open(take / STATE_DIR / "lock", "w")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(f"{take}: another mocap run is working on this take") from None
        yield
    finally:
        fh.close()


class TakeFailed(UserError):
    """A step of a take failed: its message, with the steps until then (the failed one last,
    with the warnings it printed) and the log, for mocap batch to report."""

    def __init__(self, message: str, steps: list[dict], log: Path):
        super().__init__(message)
        self.steps, self.log = steps, log


class _Stderr(io.StringIO):
    """A command's stderr, kept apart (for its warning lines) and copied into its whole output."""

    def __init__(self, whole: io.StringIO):
        super().__init__()
        self.whole = whole

    def write(self, text: str) -> int:
        self.whole.write(text)
        return super().write(text)


def run_mocap(argv: tuple[str, ...], log, warn=None) -> None:
    """One mocap command in this process, its output into ``log`` and each of its warning lines
    (without "warning: ") to ``warn``; a failure raises UserError with the command's one-line
    message, after its warnings."""
    from server.cli import EXIT_INTERRUPTED, main

    out = io.StringIO()
    err = _Stderr(out)
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    text = out.getvalue()
    log.write(f"$ mocap {' '.join(argv)}\n{text}")
    log.flush()
    for line in err.getvalue().splitlines():
        if warn and line.startswith(WARNING_PREFIX):
            warn(line[len(WARNING_PREFIX):].strip())
    if code == EXIT_INTERRUPTED:  # Ctrl-C, which the command caught: the run stops as a whole
        raise KeyboardInterrupt
    if code:
        errors = [line.split(": error: ", 1)[1] for line in text.splitlines() if ": error: " in line]
        raise UserError((errors or text.strip().splitlines() or ["failed"])[-1].strip())


def run_take(take: Path, progress=None, overwrite: bool = False) -> dict:
    """Run the take's steps that are not done; returns what was done (``mocap run``,
    ``mocap batch``): each step's status is "done", "up to date" or "kept (edited)" (with a
    ``note`` naming the outputs kept as edited), and the ``warnings`` its commands printed this
    run; ``log``: the file that holds the commands' whole output. ``progress(step, state)`` is
    told "running (WHY)" as a step starts (``why_it_runs``, also each run step's "why"),
    "warning: LINE" for each warning it prints, or the status of a step that is done. Raises
    TakeFailed with the failing step's message, or UserError
    before anything is written where the recordings do not match the calibration, or where a
    step would replace an output no run made (``overwrite`` allows it)."""
    take = Path(take).resolve()
    plan = plan_take(take)
    try:
        check_recordings(plan)
    except UserError as exc:  # the calibration read as the import will read it: its advice names options
        raise UserError(f"{exc}{config_key_note(str(exc))}") from None
    t0 = time.perf_counter()
    steps = []
    log_path = take / STATE_DIR / "run.log"
    with take_lock(take):
        if not overwrite:
            check_replaceable(take, plan)
        said = set()  # warnings shown to the user in this run
        with open(log_path, "a") as log:
            for step in plan.steps:
                status = done_status(take, step)
                if status is None:
                    steps.append({"step": step.name, "status": "failed", "warnings": []})
                    try:
                        steps[-1].update(_run_step(take, plan, step, log, progress, steps[-1], said))
                    except UserError as exc:
                        raise TakeFailed(str(exc), steps, log_path) from None
                    continue
                steps.append({"step": step.name, "status": status, "seconds": 0.0, "warnings": []})
                if status == KEPT_EDITED:
                    edited = edited_outputs(take, plan, step)
                    steps[-1]["note"] = (f"kept {', '.join(edited)} as edited since mocap run made "
                                         f"{'it' if len(edited) == 1 else 'them'}")
                    log.write(f"{step.name}: {steps[-1]['note']}\n")
                if progress:
                    progress(step.name, status)
    ran = [s for s in steps if s["status"] == "done"]
    return {"name": take.name, "path": str(take), "status": "done" if ran else "skipped", "steps": steps,
            "result": str(plan.result), "log": str(log_path), "seconds": time.perf_counter() - t0,
            **result_figures(plan.result)}


def config_key_note(message: str) -> str:
    """" (in Config.toml: --units is [calibration] units)" for the options a step's error names,
    which a user of mocap run never typed; "" where it names none."""
    named = [f"{option} is {key}" for option, key in OPTION_KEYS.items()
             if re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", message)]
    return f" (in Config.toml: {'; '.join(named)})" if named else ""


def _run_step(take: Path, plan: TakePlan, step: Step, log, progress, entry: dict, said: set) -> dict:
    """Run one step's commands and leave its record; ``entry`` (the step's line of what was
    done) gets why it runs (``why_it_runs``) and the warnings they print (which go to
    ``progress`` as they come, each once in a run: ``said`` holds those an earlier step said,
    as every step that reads a calibration in the wrong units warns of it). A fit that an earlier
    run started with the same settings and inputs is continued, any other fit replaces what is
    there."""
    pending, now = _pending_path(take, step.name), _pending(step)  # the inputs fingerprinted once
    resume = step.name == "fit" and (plan.result / "poses.jsonl").exists() and _read_json(pending) == now
    why = entry["why"] = why_it_runs(take, step, now["inputs"], resume)
    warnings = entry["warnings"]
    write_text(pending, json.dumps(now, indent=1))  # before the record goes: the outputs stay the run's
    record = _record_path(take, step.name)
    record.unlink(missing_ok=True)  # outputs being replaced: no longer up to date
    s0 = time.perf_counter()
    if progress:
        progress(step.name, f"running ({why})")
    log.write(f"{step.name}: running ({why})\n")

    def warn(line: str) -> None:
        line += config_key_note(line)  # its advice names options, as its errors' does
        warnings.append(line)
        if progress and line not in said:
            said.add(line)
            progress(step.name, f"{WARNING_PREFIX}{line}")

    for command in step.commands:
        if step.name == "fit":
            command += ("--resume",) if resume else ("--overwrite",)
        try:
            run_mocap(command, log, warn)
        except UserError as exc:
            raise UserError(f"{step.name}: {exc}{config_key_note(str(exc))}") from None
    _note_made(take, plan, step)
    write_text(record, json.dumps(_record(step), indent=1))
    pending.unlink()
    return {"step": step.name, "status": "done", "seconds": time.perf_counter() - s0}


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def result_figures(result: Path) -> dict:
    """Frames, seconds per frame, the actor's size, the fit quality (the mean XOR share, its two
    sides, the frames flagged, the share of the masks cleared before it) and accuracy (where
    there was truth) of a result folder."""
    try:
        summary = json.loads((result / "summary.json").read_text())
    except (OSError, ValueError):
        return {}
    frames = summary.get("frames") or 0
    # the whole take's time (after a --resume, this run's wall time alone would be a part of it);
    # summaries older than take_seconds have wall_seconds only
    seconds = summary.get("take_seconds", summary.get("wall_seconds"))
    out = {"frames": frames, "seconds_per_frame": seconds / frames if frames and seconds else None}
    for key in ("actor_scale", "mean_joint_error_mm", "max_joint_error_mm"):
        if key in summary:
            out[key] = summary[key]
    quality = summary.get("fit_quality") or {}
    for key in ("mean_xor_share", "mean_outside_share", "mean_missed_share"):
        if key in quality:
            out[key] = quality[key]
    if "frames_flagged" in quality:
        out["frames_flagged"] = len(quality["frames_flagged"])
    if summary.get("foreground_left_out"):  # the XOR shares are against the masks so cleared
        out["cleared_share"] = summary["foreground_left_out"]["share"]
        segmented = summary["foreground_left_out"].get("fit_quality_before_clearing", {})
        if "mean_xor_share" in segmented:
            out["xor_share_before_clearing"] = segmented["mean_xor_share"]
    return out


def frames_done(take: Path) -> tuple[int, int | None]:
    """(frames fitted so far, frames of the take if known): for a batch's progress display."""
    try:
        config = take_config(take)
    except UserError:
        return 0, None
    result = take / config.get("take", "result") / "poses.jsonl"
    done = result.read_bytes().count(b"\n") if result.is_file() else 0
    total = None
    for seq in (take, take / config.get("take", "sequence")):
        try:
            total = len(json.loads((seq / "sequence.json").read_text())["frames"])
            break
        except (OSError, ValueError, KeyError, TypeError):
            continue
    if total and config.get("fit", "frames"):
        total = min(total, config.get("fit", "frames"))
    return min(done, total) if total else done, total
