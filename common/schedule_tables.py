"""Schedules as a Config.toml's tables (``[fit.schedules]``): read and checked, and written
back, so that ``mocap config show`` prints what is in force and a file can replace any schedule.
Pure data in and out; ValueError says what is wrong, naming the schedule and the stage."""
from __future__ import annotations

import difflib
from dataclasses import fields, replace

from common.search import PROPOSERS, SCHEDULES, VARIANTS, Schedule, Schedules, Stage

SCHEDULE_NAMES = tuple(f.name for f in fields(Schedules) if isinstance(f.default, Schedule))
# the budgets counted in hops or evolutions: search_hops, ..., finish_evolutions
COUNT_BUDGETS = tuple(f.name for f in fields(Schedules) if isinstance(f.default, int))
RATIOS = tuple(f.name for f in fields(Schedules) if isinstance(f.default, float))  # loss_ratio, ...
SETTINGS = SCHEDULE_NAMES + COUNT_BUDGETS + RATIOS
# the schedules that start with no fit, and the proposers that make their first starts: from the
# previous frame's fit (tracking) or from the search's starts (the others refit a fit they are given)
FIRST_PROPOSERS = {"tracking": ("start", "start_turns", "tilt_ahead"), "wide": ("starts",), "search": ("starts",)}
SCORES = ("energy", "upright")
AS_FITTED = "as-fitted"  # a stage's variants in a file: each start fitted as the fit it came from (None)


def _count(v) -> bool:
    return type(v) is int and v >= 1


def _number(v) -> bool:
    return type(v) in (int, float)


# a stage's keys beside its names -> (the check of its value, what the check wants)
_STAGE_VALUES = {
    "rounds": (_count, "an integer >= 1"),
    "beam": (_count, "an integer >= 1"),
    "min_gain": (lambda v: _number(v) and 0.0 <= v < 1.0, "a number from 0 to 1"),
    "score": (lambda v: v in SCORES, "one of " + ", ".join(SCORES)),
    "choose": (lambda v: type(v) is bool, "true or false"),
    "drop": (lambda v: isinstance(v, list) and len(v) == 2 and _count(v[0]) and _number(v[1]) and v[1] >= 1.0,
             "[rounds >= 1, ratio >= 1]"),
}


def stage_from_table(table) -> Stage:
    """A ``Stage`` from its table in a Config.toml: ``proposers`` (required), ``variants``,
    ``rounds``, ``min_gain``, ``beam``, ``score``, ``choose``, ``drop`` ([rounds, ratio]);
    ValueError saying what is wrong."""
    if not isinstance(table, dict):
        raise ValueError(f"expected a table such as {{proposers = [\"start\"]}}, got {_shown(table)}")
    known = {f.name for f in fields(Stage)}
    for key in table:
        if key not in known:
            raise ValueError(f"unknown key {key!r} (known: {', '.join(sorted(known))})")
    if "proposers" not in table:
        raise ValueError("no proposers")
    values = dict(table)
    values["proposers"] = _names(table["proposers"], PROPOSERS, "proposer")
    if "variants" in table:
        variants = table["variants"]
        values["variants"] = None if variants == AS_FITTED else _names(variants, VARIANTS, "variant",
                                                                       f" or \"{AS_FITTED}\"")
    for key, (check, wanted) in _STAGE_VALUES.items():
        if key in table and not check(table[key]):
            raise ValueError(f"{key}: expected {wanted}, got {_shown(table[key])}")
    if "min_gain" in table:
        values["min_gain"] = float(table["min_gain"])
    if "drop" in table:
        values["drop"] = (table["drop"][0], float(table["drop"][1]))
    return Stage(**values)


def _names(value, known: dict, what: str, also: str = "") -> tuple[str, ...]:
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{what}s: expected a list of names{also}, got {_shown(value)}")
    for name in value:
        if name not in known:
            raise ValueError(f"unknown {what} {name!r} (known: {', '.join(known)})")
    return tuple(value)


def stage_table(stage: Stage) -> dict:
    """``stage`` as its table in a Config.toml (the fields away from their defaults)."""
    out = {}
    for f in fields(Stage):
        value = getattr(stage, f.name)
        if f.name == "proposers" or value != f.default:
            value = AS_FITTED if f.name == "variants" and value is None else value
            out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def schedule_from_table(table) -> Schedule:
    """A ``Schedule`` from its table in a Config.toml: ``stages``, a list of stage tables
    (``stage_from_table``), and ``budget`` (evaluations; 0: no limit); ValueError naming the
    stage that is wrong."""
    if not isinstance(table, dict):
        raise ValueError(f"expected a table with stages = [...], got {_shown(table)}")
    for key in table:
        if key not in ("stages", "budget"):
            raise ValueError(f"unknown key {key!r} (known: budget, stages)")
    stages = table.get("stages")
    if not isinstance(stages, list) or not stages:
        raise ValueError("stages: expected a list of one or more stage tables")
    budget = table.get("budget", 0)
    if type(budget) is not int or budget < 0:
        raise ValueError(f"budget: expected an integer >= 0 (evaluations; 0: no limit), got {_shown(budget)}")
    out = []
    for i, stage in enumerate(stages, 1):
        try:
            out.append(stage_from_table(stage))
        except ValueError as exc:
            raise ValueError(f"stage {i}: {exc}") from None
    return Schedule(tuple(out), budget or None)


def schedule_table(schedule: Schedule) -> dict:
    """``schedule`` as its table in a Config.toml."""
    return {"stages": [stage_table(s) for s in schedule.stages], "budget": schedule.budget or 0}


def schedules_from_table(table) -> Schedules:
    """``Schedules`` from a Config.toml's ``[fit.schedules]`` table over ``SCHEDULES``: each
    schedule given replaces the default one whole; ValueError naming the schedule."""
    if not isinstance(table, dict):
        raise ValueError(f"expected a table, got {_shown(table)}")
    values = {}
    for name, value in table.items():
        if name in COUNT_BUDGETS:
            if type(value) is not int or value < 0:
                raise ValueError(f"{name}: expected an integer >= 0, got {_shown(value)}")
            values[name] = value
        elif name in RATIOS:
            if not (_number(value) and 1.0 < value < 10.0):
                raise ValueError(f"{name}: expected a number between 1 and 10 (times), got {_shown(value)}")
            values[name] = float(value)
        elif name in SCHEDULE_NAMES:
            try:
                values[name] = schedule_from_table(value)
                if name == "after_hops" and values[name].budget:
                    raise ValueError("budget: added to a refinement's stages, it runs on the refinement's budget")
            except ValueError as exc:
                raise ValueError(f"{name}: {exc}") from None
        else:
            near = difflib.get_close_matches(name, SETTINGS, n=1)
            raise ValueError(f"unknown schedule {name!r}{f' (did you mean {near[0]!r}?)' if near else ''} "
                             f"(known: {', '.join(SETTINGS)})")
    return replace(SCHEDULES, **values)


def check_first_starts(schedules: Schedules, options) -> None:
    """ValueError where a schedule that starts with no fit (``FIRST_PROPOSERS``) has a first
    stage that makes no start under ``options`` (FitOptions: a variant such as ``polish`` fits
    nothing where its rounds are 0): it would end with nothing to choose."""
    for name, proposers in FIRST_PROPOSERS.items():
        first = getattr(schedules, name).stages[0]
        if not set(first.proposers) & set(proposers):
            raise ValueError(f"{name}: stage 1 makes no start: its proposers need one of {', '.join(proposers)}")
        if first.variants is None or all(VARIANTS[v](options) is None for v in first.variants):
            raise ValueError(f"{name}: stage 1 makes no start: its variants fit nothing with these settings "
                             f"({'as-fitted' if first.variants is None else ', '.join(first.variants)})")


def schedules_table(schedules: Schedules) -> dict:
    """``schedules`` as a Config.toml's ``[fit.schedules]`` table."""
    return {name: schedule_table(getattr(schedules, name)) for name in SCHEDULE_NAMES} | {
        name: getattr(schedules, name) for name in COUNT_BUDGETS + RATIOS}


def _shown(value) -> str:
    """A value as a Config.toml spells it, for an error line."""
    return str(value).lower() if isinstance(value, bool) else repr(value)
