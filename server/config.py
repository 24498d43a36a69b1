"""Project configuration: ``Config.toml`` files over typed defaults.

A project folder holds a ``Config.toml`` and any number of takes below it; a take's own
``Config.toml`` overrides keys of the project's, key by key (Pose2Sim's cascade). Every key is
declared once in ``SETTINGS`` with its type, default and meaning; a file with an unknown
section or key, or a value of the wrong type or range, is refused naming the file and key.
``Config.source(section, key)`` says where a value in force came from (``mocap config show``).

Paths in a file (``[calibration] file``) are relative to the folder of the file that sets them.
"""
from __future__ import annotations

import difflib
import json
import math
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from common.errors import InputFileError, UserError
from common.export import ALL_FORMATS, FORMATS
from common.fitting import ENERGY_BACKENDS, FitOptions
from common.schedule_tables import COUNT_BUDGETS, RATIOS, SCHEDULE_NAMES, schedules_from_table, schedules_table
from common.segmentation import METHODS
from common.sequence import MAX_MASK_THRESHOLD
from common.world import UP_CHOICES
from server.commands.import_video import MISSING_FRAMES

CONFIG_FILE = "Config.toml"
DEFAULT = "default"
MIN_ACTOR_HEIGHT, MAX_ACTOR_HEIGHT = 0.5, 3.0  # metres: [fit] actor_height and mocap fit --actor-height


@dataclass(frozen=True)
class Setting:
    section: str
    key: str
    default: Any
    kind: type | tuple[type, ...]  # int, float, str, bool, list (of str), dict (str -> int), or a tuple of these
    help: str
    check: Callable[[Any], bool] | None = None  # a further condition on the value
    wanted: str = ""  # what the check wants, for the error line
    structured: Callable[[Any], Any] | None = None  # checks a table of tables; ValueError says what is wrong

    def validate(self, value, where: str):
        """The value if it has this setting's type and passes its check, else InputFileError."""
        kind = self.kind
        ok = isinstance(value, kind) and not (kind is int and isinstance(value, bool))
        if float in _kinds(kind) and isinstance(value, int) and not isinstance(value, bool):
            value, ok = float(value), True
        if ok and isinstance(value, float):
            ok = math.isfinite(value)
        if ok and kind is list:
            ok = all(isinstance(v, str) for v in value)
        if ok and self.structured is not None:
            try:
                self.structured(value)
            except ValueError as exc:
                raise InputFileError(where, f"[{self.section}.{self.key}] {exc}") from None
        elif ok and kind is dict:
            ok = all(isinstance(v, int) and not isinstance(v, bool) for v in value.values())
        if ok and self.check is not None:
            ok = self.check(value)
        if not ok:
            wanted = self.wanted or {int: "an integer", float: "a finite number", str: "a string", bool: "true or false",
                                     list: "a list of strings", dict: "a table of integers"}[kind]
            shown = str(value).lower() if isinstance(value, bool) else repr(value)  # as the TOML file spells it
            raise InputFileError(where, f"[{self.section}] {self.key}: expected {wanted}, got {shown}")
        return value


def _kinds(kind) -> tuple[type, ...]:
    return kind if isinstance(kind, tuple) else (kind,)


def _at_least(n):
    return lambda v: v >= n


def _one_of(choices):
    return lambda v: v in choices


def _height_or_auto(value) -> bool:
    """Metres within mocap fit --actor-height's range (a number, or a number as text), or "auto"."""
    if value == "auto":
        return True
    try:
        return MIN_ACTOR_HEIGHT <= float(value) <= MAX_ACTOR_HEIGHT
    except ValueError:
        return False


# Named speed settings ([fit] keys over the defaults); `mocap bench presets` measures each.
PRESETS = {
    # online: one round of starts a frame (the previous pose; moved on as it moved; tilted
    # ahead while the pelvis tilts), the limbs re-detected; no turns, no polish, no refinement.
    # The start moved on took the turns' place: with it, the three development clips from the
    # truth (walk, dance, basketball) track at 11.9 / 14.5 / 14.2 mm mean for 0.24 s a frame
    # (walk from the search, `mocap bench presets`), against 11.2 / 15.1 / 12.4 for 0.33 s
    # with the turns and no start moved on (docs/accuracy.md, "The fast preset's start moved on")
    "fast": {"turn_hypotheses": 0, "track_moved_on": True, "polish_iterations": 0, "refine_passes": 0},
    "default": {},
    "best": {"refine_passes": 2, "refine_search": True, "refine_hops": 60},  # offline work
}
PRESET_KEYS = frozenset(("fit", key) for values in PRESETS.values() for key in values)


SETTINGS: tuple[Setting, ...] = (
    Setting("take", "sequence", "sequence", str, "folder (in the take) the take's videos or images are imported into"),
    Setting("take", "result", "result", str, "result folder, relative to the take"),
    Setting("calibration", "file", "", str, "calibration file or folder (default: calibration.json, calibration.toml, "
            "Calib.toml, a calibration/ folder or intri.yml + extri.yml, in the take, else in the project)"),
    Setting("calibration", "units", "", str, "units of a calibration that does not say: m, cm or mm",
            _one_of(("", "m", "cm", "mm")), "one of m, cm, mm"),
    Setting("calibration", "up", "auto", str, "the world's up axis", _one_of(UP_CHOICES),
            "one of " + ", ".join(UP_CHOICES)),
    Setting("import", "start", 0, int, "first source frame", _at_least(0), "an integer >= 0"),
    Setting("import", "stop", 0, int, "source frame to stop before (0: all)", _at_least(0), "an integer >= 0"),
    Setting("import", "step", 1, int, "keep every STEP-th frame", _at_least(1), "an integer >= 1"),
    Setting("import", "fps", 0.0, float, "frame rate of image folders (0: the video's, else 30)", _at_least(0.0),
            "a number >= 0"),
    Setting("import", "offsets", {}, dict, "per camera: its frame i + N is the others' frame i"),
    Setting("import", "missing_frames", "error", str, "a frame number some cameras have and others lack: error, "
            "or skip: leave it out of every camera", _one_of(MISSING_FRAMES), "one of " + ", ".join(MISSING_FRAMES)),
    Setting("segmentation", "method", "cheung", str, "background subtraction method", _one_of(tuple(METHODS)),
            "one of " + ", ".join(sorted(METHODS))),
    Setting("fit", "preset", DEFAULT, str, "named settings under the [fit] keys a Config.toml sets: fast (online), "
            "default, best (offline), as mocap fit --preset", _one_of(tuple(PRESETS)), "one of " + ", ".join(PRESETS)),
    Setting("fit", "frames", 0, int, "fit only the first N frames (0: all)", _at_least(0), "an integer >= 0"),
    Setting("fit", "energy", "cpu", str, "energy backend", _one_of(ENERGY_BACKENDS),
            "one of " + ", ".join(ENERGY_BACKENDS)),
    Setting("fit", "iterations", FitOptions.max_iterations, int, "rounds per frame", _at_least(1), "an integer >= 1"),
    Setting("fit", "turn_hypotheses", FitOptions.turn_hypotheses, int, "as mocap fit --turn-hypotheses",
            _at_least(0), "an integer >= 0"),
    Setting("fit", "track_moved_on", FitOptions.track_moved_on, bool, "as mocap fit --track-moved-on"),
    Setting("fit", "polish_iterations", FitOptions.polish_iterations, int, "as mocap fit --polish-iterations",
            _at_least(0), "an integer >= 0"),
    Setting("fit", "refine_passes", FitOptions.refine_passes, int, "as mocap fit --refine-passes", _at_least(0),
            "an integer >= 0"),
    Setting("fit", "refine_search", False, bool, "as mocap fit --refine-search"),
    Setting("fit", "refine_hops", FitOptions.refine_hops, int, "as mocap fit --refine-hops", _at_least(0),
            "an integer >= 0"),
    Setting("fit", "refine_chunk_frames", FitOptions.refine_chunk_frames, int, "as mocap fit --refine-chunk-frames",
            _at_least(0), "an integer >= 0"),
    Setting("fit", "init", "", str, "first-frame start: auto, truth or standing (default: truth where there is one)",
            _one_of(("", "auto", "truth", "standing")), "one of auto, truth, standing"),
    Setting("fit", "actor_height", "auto", (float, str), "the actor's height in metres, or auto", _height_or_auto,
            f"metres ({MIN_ACTOR_HEIGHT:g} to {MAX_ACTOR_HEIGHT:g}) or \"auto\""),
    Setting("fit", "clean_masks", True, bool, "drop silhouette blobs the other cameras do not support"),
    Setting("fit", "mask_threshold", -1, int, "silhouettes given as grey or colour images: pixels brighter than N "
            "are foreground, as mocap fit --mask-threshold (-1: the masks must be black and white)",
            lambda v: -1 <= v < MAX_MASK_THRESHOLD, f"an integer from -1 to {MAX_MASK_THRESHOLD - 1}"),
    # the search's own knobs: no command-line option of their own (mocap fit --set fit.KEY=VALUE)
    Setting("fit", "grid_steps", FitOptions.grid_steps, int, "grid points per limb parameter", _at_least(1),
            "an integer >= 1"),
    Setting("fit", "grid_range", FitOptions.grid_range_rad, float, "limb grid half-width, radians", _at_least(0.0),
            "a number >= 0"),
    Setting("fit", "turn_step", FitOptions.turn_step_rad, float, "the turn hypotheses' step about the vertical, "
            "radians", lambda v: 0.0 < v < math.pi, "a number between 0 and pi"),
    Setting("fit", "spine_twist_prior", FitOptions.spine_twist_prior, float, "how hard the torso's fit resists "
            "twisting the chest against the pelvis, full-resolution silhouette pixels per rad^2 (the twist hardly "
            "shows in silhouettes; lower it for dancers who twist a lot, 0: off)", _at_least(0.0), "a number >= 0"),
    Setting("fit", "redetect", FitOptions.redetect_limbs, bool, "search one limb per frame over its whole range "
            "(lost-limb recovery)"),
    Setting("fit", "prerender", FitOptions.prerender, bool, "render the still parts once per limb solve (false: "
            "every part in every evaluation, the same energies, slower)"),
    Setting("fit", "schedules", {}, dict, "the search's schedules where not the defaults: [fit.schedules.NAME] "
            "stages = [{proposers = [...], variants = [...], ...}, ...], budget = evaluations; NAME one of "
            + ", ".join(SCHEDULE_NAMES) + "; the budgets of hops and evolutions " + ", ".join(COUNT_BUDGETS)
            + " = N; the ratios " + ", ".join(RATIOS) + " = R (docs/fitting.md, \"Schedules\")",
            wanted="a table of schedules", structured=schedules_from_table),
    Setting("fit", "threads", 0, int, "single process: starts and limbs fitted at once (0: every core); "
            "the poses are the same for any number", _at_least(0), "an integer >= 0"),
    Setting("export", "formats", ["bvh", "trc", "csv"], list, "formats written into the result folder "
            "([\"all\"]: every one, as mocap export --format all)",
            lambda v: all(f in FORMATS or f == ALL_FORMATS for f in v), "a list of " + ", ".join(FORMATS)
            + f", or [\"{ALL_FORMATS}\"]"),
    Setting("report", "enabled", True, bool, "write report.html and pictures"),
    Setting("report", "gif", True, bool, "also the animated sequence.gif (the slowest picture)"),
)
_BY_KEY = {(s.section, s.key): s for s in SETTINGS}
SECTIONS = tuple(dict.fromkeys(s.section for s in SETTINGS))
# the [fit] keys with no mocap fit option of their own (--set fit.KEY=VALUE sets them)
SEARCH_KNOBS = ("grid_steps", "grid_range", "turn_step", "spine_twist_prior", "redetect", "prerender", "schedules")
# keys a take's fit record holds only where set away from their default: added after takes were
# fitted without them, they must not refit those takes
RECORDED_WHEN_SET = SEARCH_KNOBS + ("mask_threshold",)


SCHEDULES_KEY = ("fit", "schedules")


def merged(values: dict, key: tuple[str, str], value):
    """``value`` for ``key`` over what ``values`` holds for it: a later file's (or ``--set``'s)
    ``[fit.schedules]`` replaces the schedules it names and keeps the others; any other key's
    value replaces the earlier one whole."""
    return values.get(key, {}) | value if key == SCHEDULES_KEY else value


def setting_default(section: str, key: str):
    return _BY_KEY[(section, key)].default


def read_config_file(path: Path) -> dict[tuple[str, str], Any]:
    """{(section, key): value} of one Config.toml, every key known and checked."""
    try:
        doc = tomllib.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError:
        raise InputFileError(path, "not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputFileError(path, f"not valid TOML ({exc})") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror or exc})") from None
    values = {}
    for section, table in doc.items():
        if section not in SECTIONS:
            raise InputFileError(path, f"unknown section [{section}] (known: {', '.join(SECTIONS)})")
        if not isinstance(table, dict):
            raise InputFileError(path, f"{section}: expected a [{section}] table")
        for key, value in table.items():
            setting = _BY_KEY.get((section, key))
            if setting is None:
                keys = [s.key for s in SETTINGS if s.section == section]
                near = difflib.get_close_matches(key, keys, n=1)
                raise InputFileError(path, f"[{section}] unknown key {key!r}"
                                           f"{f' (did you mean {near[0]!r}?)' if near else ''} (known: {', '.join(keys)})")
            value = setting.validate(value, str(path))
            if (section, key) == ("calibration", "file") and value:
                value = str((path.parent / value).resolve())
            values[(section, key)] = value
    return values


@dataclass(frozen=True)
class Config:
    """The settings in force for one take, and the file each came from (``sources``, by
    (section, key), and by ("fit.schedules", name) for each schedule a file names)."""

    values: dict
    sources: dict

    def get(self, section: str, key: str):
        return self.values[(section, key)]

    def source(self, section: str, key: str) -> str:
        return self.sources[(section, key)]

    def section(self, name: str) -> dict:
        return {k: v for (s, k), v in self.values.items() if s == name}

    def lines(self) -> list[str]:
        """``[section] key = value   # source`` for every setting (``mocap config show``); the
        schedules one a line, ``[fit.schedules] NAME = {...}``, each as in force."""
        out = []
        for s in SETTINGS:
            value, source = self.get(s.section, s.key), self.source(s.section, s.key)
            if (s.section, s.key) == SCHEDULES_KEY:
                for name, table in schedules_table(schedules_from_table(value)).items():
                    where = self.sources.get(("fit.schedules", name), DEFAULT)
                    out.append(f"[fit.schedules] {name} = {toml_value(table)}   # {where}")
            else:
                out.append(f"[{s.section}] {s.key} = {toml_value(value)}   # {source}")
        return out


BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def toml_value(value) -> str:
    """``value`` (a setting's: bool, int, float, str, list or dict) as TOML writes it, so that
    what ``mocap config`` prints can be pasted into a Config.toml."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)  # Python's int and finite float spellings are TOML's
    if isinstance(value, str):
        # a JSON string is a TOML basic string, but for DEL, which TOML wants escaped
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        items = (f"{k if BARE_KEY.fullmatch(k) else toml_value(k)} = {toml_value(v)}" for k, v in value.items())
        return "{" + ", ".join(items) + "}"
    raise TypeError(f"no TOML spelling for {type(value).__name__}")


def load_config(files: list[Path]) -> Config:
    """Defaults, then each existing file of ``files`` in order (project first, take last)."""
    values = {(s.section, s.key): s.default for s in SETTINGS}
    sources = dict.fromkeys(values, DEFAULT)
    for path in files:
        if path.is_file():
            for key, value in read_config_file(path).items():
                if key == SCHEDULES_KEY:
                    sources.update({("fit.schedules", name): str(path) for name in value})
                values[key], sources[key] = merged(values, key, value), str(path)
    preset = values[("fit", "preset")]
    for key, value in PRESETS[preset].items():  # under the keys a file sets, over the defaults
        if sources[("fit", key)] == DEFAULT:
            values[("fit", key)], sources[("fit", key)] = value, f"preset {preset}"
    return Config(values, sources)


# a setting's command-line option where it is not --key-with-dashes
OPTION_NAMES = {("calibration", "file"): "--calibration", ("import", "offsets"): "--offset",
                ("fit", "clean_masks"): "--no-clean-masks"}
# the options of mocap run's steps (import-video, segment, fit) -> the Config.toml key that sets them
OPTION_KEYS = {OPTION_NAMES.get((s.section, s.key), "--" + s.key.replace("_", "-")): f"[{s.section}] {s.key}"
               for s in SETTINGS if s.section in ("calibration", "import", "segmentation", "fit")
               and s.key not in SEARCH_KNOBS}


# [section] key -> mocap fit's option (dest), and how a file's value becomes the option's value
FIT_OPTION_DESTS = {
    ("fit", "frames"): ("frames", lambda v: v or None), ("fit", "energy"): ("energy", None),
    ("fit", "iterations"): ("iterations", None), ("fit", "turn_hypotheses"): ("turn_hypotheses", None),
    ("fit", "track_moved_on"): ("track_moved_on", None),
    ("fit", "polish_iterations"): ("polish_iterations", None), ("fit", "refine_passes"): ("refine_passes", None),
    ("fit", "refine_search"): ("refine_search", None), ("fit", "refine_hops"): ("refine_hops", None),
    ("fit", "refine_chunk_frames"): ("refine_chunk_frames", None),
    ("fit", "init"): ("init", lambda v: v or None), ("fit", "actor_height"): ("actor_height", None),
    ("fit", "clean_masks"): ("clean_masks", None), ("fit", "threads"): ("threads", None),
    ("fit", "mask_threshold"): ("mask_threshold", lambda v: None if v < 0 else v),
    ("fit", "grid_steps"): ("grid_steps", None), ("fit", "grid_range"): ("grid_range", None),
    ("fit", "turn_step"): ("turn_step", None), ("fit", "spine_twist_prior"): ("spine_twist_prior", None),
    ("fit", "redetect"): ("redetect", None), ("fit", "prerender"): ("prerender", None),
    ("fit", "schedules"): ("schedules", None),
    ("calibration", "units"): ("units", lambda v: v or None), ("calibration", "up"): ("up", None),
    ("calibration", "file"): ("calibration", lambda v: Path(v) if v else None),
}


def _as_option_defaults(values: dict) -> dict:
    """{(section, key): value} -> {mocap fit's option dest: its value}."""
    out = {}
    for key, value in values.items():
        if key in FIT_OPTION_DESTS:
            dest, convert = FIT_OPTION_DESTS[key]
            out[dest] = convert(value) if convert else value
    return out


def fit_option_defaults(preset: str | None, path: Path | None, settings: list[str] = ()) -> dict:
    """{option dest: value} that replace ``mocap fit``'s built-in defaults: a preset's, then the
    [fit] and [calibration] keys of a Config.toml (``--config``), then ``settings`` (``--set``
    SECTION.KEY=VALUE, ``parse_setting``); options given still win."""
    given = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise InputFileError(path, "missing (--config names a Config.toml)")
        given = read_config_file(path)
    for key, value in (parse_setting(text) for text in settings):
        given[key] = merged(given, key, value)
    # --preset over the file's [fit] preset; the file's own keys over either
    values = {("fit", k): v for k, v in PRESETS[preset or given.get(("fit", "preset"), DEFAULT)].items()}
    values.update(given)
    return _as_option_defaults(values)


def parse_setting(text: str) -> tuple[tuple[str, str], Any]:
    """``SECTION.KEY=VALUE`` (``mocap fit --set``) -> ((section, key), value), the value read as
    TOML (``fit.grid_steps=7``, ``fit.redetect=false``; a bare word as text: ``calibration.units=mm``)
    and checked as a Config.toml's; UserError naming --set and the key."""
    name, sep, literal = text.partition("=")
    section, dot, key = name.strip().partition(".")
    if not sep or not dot:
        raise UserError(f"--set: expected SECTION.KEY=VALUE (e.g. fit.grid_steps=7), got {text!r}")
    setting = _BY_KEY.get((section, key))
    if setting is not None and section not in ("fit", "calibration"):
        raise UserError(f"--set: {name.strip()} is no key of mocap fit's: --set takes the [fit] and [calibration] "
                        f"ones ([{section}] is mocap run's, in a Config.toml)")
    if setting is None or section not in ("fit", "calibration"):
        keys = [f"{s.section}.{s.key}" for s in SETTINGS if s.section in ("fit", "calibration")]
        near = difflib.get_close_matches(name.strip(), keys, n=1)
        raise UserError(f"--set: unknown key {name.strip()!r}{f' (did you mean {near[0]!r}?)' if near else ''} "
                        "(mocap config keys lists them; --set takes the [fit] and [calibration] ones)")
    try:
        value = tomllib.loads(f"v = {literal.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = literal.strip()  # a bare word: text
    try:
        return (section, key), setting.validate(value, "--set")
    except InputFileError as exc:
        raise UserError(str(exc)) from None