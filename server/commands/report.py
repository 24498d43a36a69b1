"""``mocap report``: RESULT/report.html (self-contained) and the pictures in RESULT/pictures/.

    mocap report RESULT [--sequence SEQ] [--fps FPS] [--frames 0,30,60] [--cameras cam1,cam3] [--out FILE]
                        [--no-pictures] [--no-gif] [--quiet] [--json]
"""
from __future__ import annotations

import json
from pathlib import Path

from common.errors import UserError
from common.argtypes import real
from server.output import add_overwrite_argument, check_file_target, check_folder_target
from server.pictures import PICTURES_DIR, make_result_pictures
from server.report import REPORT_NAME, write_report
from server.results import frames_text, load_records


def _int_list(text: str | None, option: str) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"{option}: expected comma-separated frame numbers such as 0,30,60, got {text!r}") from None


def _name_list(text: str | None) -> list[str] | None:
    """--cameras' names; a name given twice refused (it would be drawn twice)."""
    if text is None:
        return None
    names = [v.strip() for v in text.split(",") if v.strip()]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise UserError(f"--cameras: {', '.join(twice)} given more than once")
    return names


def register(sub) -> None:
    p = sub.add_parser("report", help="write RESULT/report.html and pictures of a fit",
                       description="Write a self-contained report page (summary, plots, overlays, 3D player) "
                                   "and pictures (overlays, 3D views, GIF, plots) of a result folder.")
    p.add_argument("result", type=Path, help="result folder (poses.jsonl from mocap fit)")
    p.add_argument("--sequence", type=Path, default=None, help="the fitted sequence, if it moved since the fit")
    p.add_argument("--fps", type=real(0.0, exclusive_minimum=True), default=None,
                   help="frame rate, when the sequence is not available")
    p.add_argument("--frames", default=None, help="frame numbers to picture, comma-separated (default: a few)")
    p.add_argument("--cameras", default=None, help="camera names for overlays, comma-separated (default: up to 4)")
    p.add_argument("--out", type=Path, default=None, help="report file (default RESULT/report.html)")
    p.add_argument("--no-pictures", action="store_true", help="only the report page, no RESULT/pictures/")
    p.add_argument("--no-gif", action="store_true", help="no sequence.gif (the slowest picture)")
    add_overwrite_argument(p)
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.add_argument("--json", action="store_true", help="print the written paths as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    frames = _int_list(args.frames, "--frames")
    records = load_records(args.result)  # a result folder, readable, before its report's place is checked
    fitted = [r["frame"] for r in records]
    missing = [f for f in frames or () if f not in fitted]
    if missing:
        raise UserError(f"--frames: frame {missing[0]} was not fitted (frames fitted: {frames_text(fitted)})")
    check_file_target(args.out or args.result / REPORT_NAME, args.overwrite, given=args.out is not None)
    if not args.no_pictures:
        # RESULT/pictures/: no option writes them elsewhere
        check_folder_target(args.result / PICTURES_DIR, ("*",), option=None, overwrite=args.overwrite,
                            what="set of pictures", given=False, instead="--no-pictures to write the page alone")
    cameras = _name_list(args.cameras)
    pictures = []
    if not args.no_pictures:
        pictures = make_result_pictures(args.result, args.sequence, frames, cameras, gif=not args.no_gif,
                                        quiet=args.quiet or args.json, fps=args.fps)
    report = write_report(args.result, args.sequence, frames, cameras, out=args.out, fps=args.fps)
    if args.json:
        print(json.dumps({"report": str(report), "pictures": [str(p) for p in pictures]}, indent=1))
    elif not args.quiet:
        if pictures:
            print(f"wrote {len(pictures)} pictures in {pictures[0].parent}")
        print(f"report: {report}")
    return 0
