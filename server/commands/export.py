"""``mocap export``: write a result folder's fitted motion as BVH, C3D, TRC, JSON lines or CSV.

    mocap export RESULT --format bvh|c3d|trc|json|csv|all [--out PATH] [--sequence SEQ] [--fps FPS]

One format writes ``--out`` (default ``RESULT/motion.<ext>``); ``all`` writes every format into
the folder ``--out`` (default RESULT). The frame rate comes from the sequence (summary.json
names it; ``--sequence`` when it moved) or ``--fps``. Axis conventions: docs/exports.md.
"""
from __future__ import annotations

import json
from pathlib import Path

from common.export import FORMATS, SUFFIXES, export_motion
from server.argtypes import real
from server.output import add_overwrite_argument, check_file_target, check_folder_target, replace_file
from server.pictures import load_result

EXPORT_STEM = "motion"


def register(sub) -> None:
    p = sub.add_parser("export", help="export fitted motion (BVH, C3D, TRC, JSON lines, CSV)",
                       description="Export a result folder's fitted motion. Axis conventions: docs/exports.md.")
    p.add_argument("result", type=Path, help="result folder (poses.jsonl from mocap fit)")
    p.add_argument("--format", required=True, choices=FORMATS + ("all",),
                   help="bvh (Blender), c3d, trc (OpenSim), json (JSON lines), csv, or all of them")
    p.add_argument("--out", type=Path, default=None,
                   help="file to write (default RESULT/motion.EXT); with --format all, a folder")
    p.add_argument("--sequence", type=Path, default=None, help="the fitted sequence, if it moved since the fit")
    p.add_argument("--fps", type=real(0.0, exclusive_minimum=True), default=None,
                   help="frame rate (default: the sequence's)")
    add_overwrite_argument(p)
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.add_argument("--json", action="store_true", help="print what was written as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    result = load_result(args.result, args.sequence, args.fps)
    motion = result.motion
    if args.format == "all":
        folder = args.out or args.result
        check_folder_target(folder, (), overwrite=True)  # a file, or not writable: refused
        folder.mkdir(parents=True, exist_ok=True)
        targets = [(f, folder / f"{EXPORT_STEM}{SUFFIXES[f]}") for f in FORMATS]
    else:
        targets = [(args.format, args.out or args.result / f"{EXPORT_STEM}{SUFFIXES[args.format]}")]
    for _, path in targets:  # every target checked before the first is written
        check_file_target(path, args.overwrite)
    written = []
    for fmt, path in targets:
        replace_file(path, lambda tmp: export_motion(fmt, tmp, motion))
        written.append({"format": fmt, "path": str(path), "frames": len(motion.frames), "fps": motion.fps,
                        "bytes": path.stat().st_size})
    if args.json:
        print(json.dumps(written if args.format == "all" else written[0], indent=1))
    elif not args.quiet:
        for w in written:
            print(f"wrote {w['path']} ({w['format']}, {w['frames']} frames at {w['fps']:g} fps)")
    return 0
