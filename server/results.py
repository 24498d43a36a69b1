"""A result folder's records and settings: reading poses.jsonl, run.json and --resume's checks,
and replacing the file whole."""
from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np

from common.body import PARAM_COUNT
from common.errors import InputFileError, UserError, print_warning
from common.export import FORMATS, export_name, frame_step, frames_off_step
from server.output import check_folder_target, listed, write_text

POSES_FILE = "poses.jsonl"
SUMMARY_FILE = "summary.json"
RUN_FILE = "run.json"  # the settings of the run that wrote poses.jsonl, which --resume must match
MOTION_FILE = "motion.bvh"
# the pixels a fit cleared from every frame's masks (foreground no fitted pose explains), which
# its pictures clear too
FOREGROUND_FILE = "foreground_left_out.npz"
# a result's files: not run.json, which is written before the first frame, so that a folder
# holding only that (a run stopped or refused before any frame was fitted) is no result to keep
RESULT_FILES = (POSES_FILE, SUMMARY_FILE, MOTION_FILE, FOREGROUND_FILE)
# made from a result, so stale once it is replaced (mocap report, mocap export's default names)
DERIVED_FILES = ("report.html", "pictures") + tuple(export_name(f) for f in FORMATS if export_name(f) != MOTION_FILE)


def frames_text(frames) -> str:
    """Fitted frame numbers for a message: '0..195, one in 5', '0..40', '10..38, one in 2,
    without 18', or 'none'."""
    if len(frames) == 0:
        return "none"
    step = frame_step(frames)
    off = frames_off_step(frames)
    without = f", without {listed(off)}" if off else ""
    return f"{min(frames)}..{max(frames)}" + (f", one in {step}" if step > 1 else "") + without


def stopped_note(out_dir: Path) -> str:
    """What a fit stopped by a signal leaves: where its frames are and how to go on, or that it
    stopped before its first frame (a server waiting for its clients)."""
    poses = Path(out_dir) / POSES_FILE
    if poses.is_file() and poses.stat().st_size > 0:
        return f"the frames fitted are kept in {out_dir}, and the same command with --resume continues"
    return f"stopped before its first frame was fitted; nothing is in {out_dir}"


def read_done_frames(path: Path) -> list[dict]:
    """The records of an existing poses.jsonl.

    A torn last line (a crash while it was written: no newline at its end) is dropped with a
    warning; any other line that is not a record, whose parameters are not PARAM_COUNT finite
    numbers, or whose frame does not follow the line before (lines swapped or repeated by hand)
    is an InputFileError naming it, because exports would play it backwards or twice and a
    --resume would lose or refit the frames after it.
    """
    if not path.exists():
        return []
    lines = path.read_bytes().split(b"\n")
    done = []
    for n, raw in enumerate(lines[:-1], start=1):  # lines[-1]: b"" or the torn last line
        try:
            record = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError):
            record = None
        if not (isinstance(record, dict) and isinstance(record.get("frame"), int)
                and isinstance(record.get("params"), list)):
            raise InputFileError(path, f"line {n}: not a pose record (corrupt?); repair or remove the file, "
                                       "or fit again with --overwrite")
        params = record["params"]
        if len(params) != PARAM_COUNT or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in params):
            raise InputFileError(path, f"line {n}: params: expected {PARAM_COUNT} finite numbers (frame "
                                       f"{record['frame']}); repair the line, or fit again with --overwrite")
        bad = joints_problem(record.get("joints", {}))
        if bad is not None:
            raise InputFileError(path, f"line {n}: joints: {bad} (frame {record['frame']}); repair the line, "
                                       "or fit again with --overwrite")
        if done and record["frame"] <= done[-1]["frame"]:
            raise InputFileError(path, f"line {n}: frame {record['frame']} after frame {done[-1]['frame']}: the "
                                       "records are out of order or repeated; repair the file, or fit again with "
                                       "--overwrite")
        done.append(record)
    if lines[-1].strip() and (str(path), len(lines)) not in _TORN_WARNED:  # said once, however often it is read
        _TORN_WARNED.add((str(path), len(lines)))
        print_warning(f"{path}: line {len(lines)} is incomplete (a run stopped while writing it): left out")
    return done


_TORN_WARNED: set = set()


def joints_problem(joints) -> str | None:
    """What is wrong with a record's "joints" ({name: [x, y, z]}, metres): "NAME: expected 3
    finite numbers" for the first joint that is not, None where nothing is."""
    if not isinstance(joints, dict):
        return "expected {joint: [x, y, z]}"
    for name, xyz in joints.items():
        if not (isinstance(xyz, list) and len(xyz) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in xyz)):
            return f"{name}: expected 3 finite numbers"
    return None


def settings_differences(before: dict, now: dict, prefix: str = "") -> list[str]:
    """'KEY NOW (was BEFORE)' for every setting that differs, nested keys joined by dots."""
    out = []
    for key in sorted(set(before) | set(now)):
        a, b = before.get(key), now.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += settings_differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key} {b!r} (was {a!r})")
    return out


def read_run_settings(path: Path) -> dict:
    """A run.json's settings; InputFileError where it is not a JSON object."""
    try:
        settings = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise InputFileError(path, "not valid JSON (corrupt?); fit again with --overwrite") from None
    if not isinstance(settings, dict):
        raise InputFileError(path, "expected a JSON object; fit again with --overwrite")
    return settings


def earlier_actor_scale(out_dir: Path) -> float | None:
    """The actor's size (over the body model's) of the run that --resume continues in
    ``out_dir``: its run.json's (written before its first frame), else its first record's;
    None where nothing is there to continue (a --resume into a new folder fits afresh)."""
    path = out_dir / RUN_FILE
    if path.exists():
        settings = read_run_settings(path)
        if "actor_scale" in settings:
            return float(settings["actor_scale"])
    done = read_done_frames(out_dir / POSES_FILE)
    return float(done[0].get("actor_scale", 1.0)) if done else None


def check_resume(out_dir: Path, settings: dict) -> None:
    """Refuse to continue a run with other settings than those it was started with."""
    path = out_dir / RUN_FILE
    if not path.exists():
        raise InputFileError(path, "missing: no record of the settings the earlier frames were fitted with; "
                                   "fit again with --overwrite")
    differ = settings_differences(read_run_settings(path), settings)
    if differ:
        raise UserError(f"--resume: the settings differ from the run being continued ({path}): "
                        + "; ".join(differ) + ". Pass the same options (--config, --set), or --overwrite to fit again")


def prepare_result_folder(out_dir: Path, settings: dict, resume: bool, overwrite: bool) -> list[dict]:
    """Check a result folder and make it ready for a run; returns the records being continued.

    An earlier result is refused unless ``resume`` (its settings must match, see
    ``check_resume``) or ``overwrite`` (its files, and those made from them, are removed).
    """
    earlier = check_folder_target(out_dir, RESULT_FILES, resume=resume, overwrite=overwrite)
    poses_path = out_dir / POSES_FILE
    if resume and earlier:
        check_resume(out_dir, settings)
        done = read_done_frames(poses_path)
        rewrite_complete(poses_path, done)  # drop a torn last line before appending
        return done
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in (RESULT_FILES + DERIVED_FILES) if earlier else ():
        target = out_dir / name
        if target.is_dir():
            shutil.rmtree(target)
        else:
            target.unlink(missing_ok=True)
    write_text(out_dir / RUN_FILE, json.dumps(settings, indent=1))
    return []


def rewrite_complete(path: Path, records: list[dict]) -> None:
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w") as fh:
        for r in records:
            fh.write(json.dumps(r) + "\n")
    os.replace(tmp, path)


def load_records(out_dir: Path) -> list[dict]:
    path = Path(out_dir) / POSES_FILE
    if not path.exists():
        raise InputFileError(path, "missing (not a result folder?)")
    return read_done_frames(path)


def write_foreground_left_out(out_dir: Path, pixels) -> None:
    """The pixels (K, H, W) bool a fit cleared from the masks, packed, to ``FOREGROUND_FILE``;
    the file removed where ``pixels`` is None."""
    path = Path(out_dir) / FOREGROUND_FILE
    if pixels is None:
        path.unlink(missing_ok=True)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, packed=np.packbits(pixels, axis=-1), width=pixels.shape[-1])
    os.replace(tmp, path)


def read_foreground_left_out(out_dir: Path):
    """(K, H, W) bool: the pixels the fit in ``out_dir`` cleared from the masks; None where none."""
    path = Path(out_dir) / FOREGROUND_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path) as saved:
            return np.unpackbits(saved["packed"], axis=-1, count=int(saved["width"])).astype(bool)
    except (OSError, ValueError, KeyError) as exc:
        raise InputFileError(path, f"not a mask file this program wrote ({exc}); fit again with --overwrite") from None
