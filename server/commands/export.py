"""``mocap export``: write a result folder's fitted motion as glTF, OpenSim, EasyMocap, BVH, C3D, JSON lines or CSV.

    mocap export RESULT --format glb|mot|trc|keypoints3d|bvh|c3d|json|csv|all[,...] [--out PATH]
                        [--rest apose|tpose] [--sequence SEQ] [--fps FPS]

One format writes ``--out`` (default ``RESULT/motion.<ext>``; keypoints3d is a folder,
``RESULT/motion_keypoints3d/``); several (``--format glb,trc`` or ``--format glb --format trc``)
or ``all`` write into the folder ``--out`` (default RESULT). The frame rate comes from the
sequence (summary.json names it; ``--sequence`` when it moved) or ``--fps``. Every target is
checked before the first is written (existing ones only with ``--overwrite``, or where they
hold what would be written: the fit's own motion.bvh, then left as they are, their modification
times too), and each is written beside its name and renamed over it. Axis conventions: docs/exports.md.
"""
from __future__ import annotations

import argparse
import json
import re
import tempfile
from pathlib import Path

from common.errors import UserError, print_warning
from common.export import (
    ALL_FORMATS as ALL, BVH_RESTS, DEFAULT_BVH_REST, FOLDER_FORMATS, FORMATS, SUFFIXES, export_motion, export_name,
    frames_off_step, named_formats,
)
from common.argtypes import real
from server.output import (
    add_overwrite_argument, check_file_target, check_folder_target, counted, listed, replace_file, staged_folder,
)
from server.pictures import load_result

FILE_SUFFIXES = {suffix for suffix in SUFFIXES.values() if suffix.startswith(".")}  # the formats written as files
NAMED_SUFFIXES = FILE_SUFFIXES | {".json", ".gltf"}  # a name ending so says what file it is
KEYPOINT_FILE = re.compile(r"\d+\.json")  # a keypoints3d export's files: one per frame


def check_export_name(fmt: str, path: Path) -> None:
    """A name given with --out that says another format (``--format bvh --out y.glb``, or a
    keypoints3d folder named ``k.json``) is refused: a tool would open it as that format."""
    suffix = path.suffix.lower()
    own = {SUFFIXES[fmt], *((".json",) if fmt == "json" else ())}
    if suffix in NAMED_SUFFIXES and suffix not in own:
        what = "a folder of one JSON file per frame" if fmt in FOLDER_FORMATS else f"a {SUFFIXES[fmt]} file"
        raise UserError(f"--out {path}: names a {suffix} file, and a {fmt} export is {what}; rename it, or give "
                        f"the --format it names")


def check_keypoints_folder(path: Path) -> None:
    """A keypoints3d export replaces its folder whole: one holding files no such export writes
    (a folder of the user's) is refused, --overwrite or not, so that they are not deleted."""
    if path.is_dir():
        other = sorted(e.name for e in path.iterdir() if not KEYPOINT_FILE.fullmatch(e.name))
        if other:
            raise UserError(f"{path}: holds files that are no keypoints3d export ({', '.join(other[:3])}"
                            f"{', ...' if len(other) > 3 else ''}); give a folder of its own")


def format_list(text: str) -> list[str]:
    """--format's value: comma-separated names of FORMATS, or ``all``."""
    names = [v.strip() for v in text.split(",") if v.strip()]
    unknown = [n for n in names if n not in FORMATS + (ALL,)]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown format {', '.join(unknown) or repr(text)}; choose from "
                                         f"{', '.join(FORMATS)} or {ALL} (several: comma-separated)")
    return names


def register(sub) -> None:
    p = sub.add_parser("export", help="export fitted motion (glTF, OpenSim TRC/MOT, EasyMocap, BVH, C3D, JSON lines, CSV)",
                       description="Export a result folder's fitted motion. Axis conventions and the settings for "
                                   "Blender, OpenSim and three.js: docs/exports.md.")
    p.add_argument("result", type=Path, help="result folder (poses.jsonl from mocap fit)")
    p.add_argument("--format", required=True, type=format_list, action="extend", metavar="|".join(FORMATS + (ALL,)),
                   help="glb (glTF: Blender, three.js), mot and trc (OpenSim, Pose2Sim), keypoints3d (EasyMocap, a "
                        "folder), bvh, c3d, json (JSON lines), csv, or all; several comma-separated or repeated")
    p.add_argument("--out", type=Path, default=None,
                   help="file to write (default RESULT/motion.EXT); with several formats or all, a folder")
    p.add_argument("--rest", choices=BVH_RESTS, default=DEFAULT_BVH_REST,
                   help=f"the BVH's rest pose: the body model's A-pose or a T-pose for retargeting; the motion is the "
                        f"same (default {DEFAULT_BVH_REST})")
    p.add_argument("--sequence", type=Path, default=None, help="the fitted sequence, if it moved since the fit")
    p.add_argument("--fps", type=real(0.0, exclusive_minimum=True), default=None,
                   help="the recording's frame rate, of the frame numbers (default: the sequence's); "
                        "BVH, C3D and TRC take it over the step between fitted frames")
    add_overwrite_argument(p)
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.add_argument("--json", action="store_true", help="print what was written as JSON")
    p.set_defaults(func=run)


def _write(fmt: str, path: Path, motion, rest: str) -> None:
    """One export, atomically: a file renamed over its name, a folder swapped in whole."""
    if fmt in FOLDER_FORMATS:
        with staged_folder(path) as staged:
            export_motion(fmt, staged, motion, bvh_rest=rest)
    else:
        replace_file(path, lambda tmp: export_motion(fmt, tmp, motion, bvh_rest=rest, final_path=path))


def _contents(path: Path) -> dict[str, bytes | None]:
    """{name: bytes} of a file (name "") or of a folder's entries; None for an entry that is not
    a readable file (which then never matches what an export writes)."""
    def read(f: Path) -> bytes | None:
        try:
            return f.read_bytes() if f.is_file() else None
        except OSError:
            return None
    return {f.name: read(f) for f in path.iterdir()} if path.is_dir() else {"": read(path)}


def _unchanged(fmt: str, path: Path, motion, rest: str) -> bool:
    """Whether ``path`` (a file, or a folder for FOLDER_FORMATS) holds exactly what this export
    would write there: ``mocap fit`` writes RESULT/motion.bvh, which ``--format all`` then
    writes again, and an export run twice writes the same; the same bytes lose nothing."""
    if not (path.is_dir() if fmt in FOLDER_FORMATS else path.is_file()):
        return False
    with tempfile.TemporaryDirectory() as tmp:
        again = Path(tmp) / path.name
        export_motion(fmt, again, motion, bvh_rest=rest, final_path=path)
        return _contents(again) == _contents(path)


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() else path.stat().st_size


def run(args) -> int:
    formats = named_formats(args.format)
    several = ALL in args.format or len(formats) > 1
    given = args.out is not None  # else the targets are defaults, which errors name without --out
    result = load_result(args.result, args.sequence, args.fps)
    motion = result.motion
    fixed_rate = sorted(set(formats) & {"bvh", "c3d", "trc"})
    if fixed_rate and (off := frames_off_step(motion.frames)):
        print_warning(f"{args.result}: frame{'s' if len(off) > 1 else ''} {listed(off)} of the fitted frames' step "
                      f"{'are' if len(off) > 1 else 'is'} missing: {', '.join(fixed_rate)} (one fixed rate) "
                      "play the frames after it early; glTF, MOT, CSV and JSON lines keep each frame's time")
    if several:
        folder = args.out or args.result
        if not folder.exists() and folder.suffix.lower() in FILE_SUFFIXES:  # a file's name, for a folder
            raise UserError(f"--out {folder}: several formats are written into a folder, and this names a "
                            f"{folder.suffix} file; give a folder, or one format")
        check_folder_target(folder, (), overwrite=True, given=given)  # a file, or not writable: refused
        folder.mkdir(parents=True, exist_ok=True)
        targets = [(f, folder / export_name(f)) for f in formats]
    else:
        targets = [(formats[0], args.out or args.result / export_name(formats[0]))]
        if given:
            check_export_name(formats[0], args.out)
    unchanged = set()  # targets that hold this export already: left as they are, their times too
    for fmt, path in targets:  # every target checked before the first is written
        if fmt in FOLDER_FORMATS and not path.parent.is_dir():  # as for a file: no folders made on the way
            raise UserError(f"--out {path}: folder {path.parent} does not exist")
        if _unchanged(fmt, path, motion, args.rest):
            unchanged.add(path)
        elif fmt in FOLDER_FORMATS:
            check_keypoints_folder(path)
            check_folder_target(path, ("*",), overwrite=args.overwrite, what="export", given=given)
        else:
            check_file_target(path, args.overwrite, given=given)
    written = []
    for fmt, path in targets:
        # rewritten, the same bytes would get a new modification time, and mocap run would then
        # take an export its own step made for one edited by hand
        if path not in unchanged:
            _write(fmt, path, motion, args.rest)
        entry = {"format": fmt, "path": str(path), "frames": len(motion.frames), "fps": motion.fps, "rate": motion.rate,
                 "bytes": _size(path), "unchanged": path in unchanged}
        if fmt == "bvh":
            entry["rest"] = args.rest
        written.append(entry)
    if args.json:
        print(json.dumps(written if several else written[0], indent=1))
    elif not args.quiet:
        for w in written:
            done = "left" if w["unchanged"] else "wrote"
            print(f"{done} {w['path']} ({w['format']}, {counted(w['frames'], 'frame')} at {w['rate']:g} fps)"
                  + (": it holds this export already" if w["unchanged"] else ""))
    return 0
