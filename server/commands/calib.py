"""``mocap calib``: convert calibrations between formats, show a calibration's cameras.

    mocap calib convert IN OUT [--format FMT] [--from FMT] [--units m|cm|mm] [--size WxH]
                               [--size-from CAMERA=PATH ...]
    mocap calib show FILE [--from FMT] [--units m|cm|mm] [--size WxH] [--size-from CAMERA=PATH ...]

The input format is detected (see ``common.calibration.detect_format``; a folder holding two
calibrations is refused, naming them); projection (3x4 P
files) and qualisys (.qca.txt) are read only. The output format is ``--format``, else from OUT's
name: .json -> json, .toml -> pose2sim (``--format anipose`` for aniposelib), .xml -> opencv-xml
(one camera); easymocap and opencv-xml write a folder OUT. Cameras without an image size in the
file, ``--size`` or ``--size-from`` (a camera's video, image folder or image, as import-video
reads them) get twice their principal point; ``show`` marks them with ``*``, and pose2sim and
anipose, which cannot mark a guess, are not written with one.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from common.calibration import (
    FORMATS, WRITE_FORMATS, check_sizes_writable, detect_format, load_calibration, output_format,
    save_calibration,
)
from common.camera import Studio
from common.errors import UserError, print_warning
from common.world import UP_CHOICES, WorldFrame, below_floor_warning, resolve_world
from server.frame_sources import FrameSource
from server.output import (add_overwrite_argument, add_units_argument, check_file_target, check_folder_target,
                           replace_file, staged_folder)


def register(subparsers) -> None:
    parser = subparsers.add_parser("calib", help="convert or show camera calibrations",
                                   description="Convert or show camera calibrations (" + ", ".join(FORMATS) + ").")
    sub = parser.add_subparsers(dest="calib_command", metavar="ACTION")
    sub.required = True

    convert = sub.add_parser("convert", help="convert a calibration to another format")
    convert.add_argument("input", metavar="IN", help="calibration file or folder")
    convert.add_argument("output", metavar="OUT", help="file or folder to write")
    convert.add_argument("--format", choices=WRITE_FORMATS,
                         help="output format (default: from OUT's extension; .toml means pose2sim)")
    _input_options(convert)
    add_overwrite_argument(convert)
    convert.set_defaults(func=run_convert)

    show = sub.add_parser("show", help="print a table of the cameras in a calibration")
    show.add_argument("input", metavar="FILE", help="calibration file or folder")
    _input_options(show)
    show.set_defaults(func=run_show)


def _input_options(parser) -> None:
    parser.add_argument("--from", dest="input_format", choices=FORMATS, help="input format (default: detected)")
    add_units_argument(parser)
    parser.add_argument("--size", metavar="WxH", help="image size for cameras whose file gives none")
    parser.add_argument("--size-from", nargs="+", action="extend", default=[], metavar="CAMERA=PATH",
                        help="a camera's video, image folder or image: its size replaces a guessed one and "
                             "must agree with the file's")
    parser.add_argument("--up", choices=UP_CHOICES, default="auto",
                        help="the world's up axis (default auto: found from the cameras); printed, and a warning "
                             "when cameras would stand below the floor; files keep their own frame")


def _parse_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise UserError(f"--size: expected WIDTHxHEIGHT in pixels such as 1920x1080, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def _image_sizes(values: list[str]) -> dict[str, tuple[int, int]]:
    """Camera -> (width, height) of the first frame of each --size-from CAMERA=PATH."""
    sizes = {}
    for value in values:
        camera, sep, path = value.partition("=")
        if not sep or not camera or not path:
            raise UserError(f"--size-from: expected CAMERA=PATH, got {value!r}")
        if camera in sizes:
            raise UserError(f"--size-from {camera}: given twice")
        height, width = FrameSource(camera, Path(path), "--size-from").first().shape[:2]
        sizes[camera] = (width, height)
    return sizes


def _load(args, warn=print_warning) -> Studio:
    return load_calibration(args.input, units=args.units, fmt=args.input_format, size=_parse_size(args.size),
                            warn=warn, image_sizes=_image_sizes(args.size_from), images="--size-from")


def run_convert(args) -> int:
    fmt = output_format(args.output, args.format)  # fail before reading when OUT is ambiguous
    out = Path(args.output)
    single_file = fmt in ("json", "pose2sim", "anipose") or out.suffix.lower() == ".xml"
    if single_file:
        check_file_target(out, args.overwrite, option="OUT")
    else:
        check_folder_target(out, ("*",), option="OUT", overwrite=args.overwrite, what="calibration")
    warnings: list[str] = []  # shown once written: a refused write says one thing, its error
    studio = _load(args, warnings.append)
    check_sizes_writable(studio, out, fmt)
    if single_file:
        replace_file(out, lambda tmp: save_calibration(studio, tmp, fmt))
    else:  # a folder of per-camera files, swapped in whole
        with staged_folder(out, merge=True) as staged:
            save_calibration(studio, staged, fmt)
    for line in warnings:
        print_warning(line)
    print(f"wrote {len(studio)} cameras to {args.output} ({fmt})")
    print(world_line(studio, resolve_world(studio, args.up), args.up))
    return 0


def run_show(args) -> int:
    studio = _load(args)
    fmt = args.input_format or detect_format(args.input)
    print(f"{args.input}: {len(studio)} cameras ({fmt}; positions in metres)")
    world = resolve_world(studio, args.up)
    print(studio_table(studio, world))
    guessed = [c.name for c in studio if c.size_guessed]
    if guessed:
        print(f"* size guessed as twice the principal point: {', '.join(guessed)} "
              "(pass --size WxH or --size-from CAMERA=PATH)")
    print(world_line(studio, world, args.up))
    return 0


def world_line(studio: Studio, world: WorldFrame, up: str) -> str:
    """'up axis: -z (found from the cameras)' of ``world``, resolved from ``up`` ("auto": found);
    a warning on stderr naming cameras below the floor."""
    warning = below_floor_warning(studio, world)
    if warning:
        print_warning(warning)
    how = "found from the cameras" if up == "auto" else "as given"
    return (f"up axis: {world.up} ({how}); fitting turns it to +z; poses.jsonl and the CSV, C3D, JSON lines "
            "and keypoints3d exports keep this frame (every format's axes: docs/exports.md)")


def studio_table(studio: Studio, world: WorldFrame | None = None) -> str:
    """One line per camera: name, image size (``*``: guessed), focal lengths (px), centre position (m),
    distortion; with ``world``, also the centre's height above the
    floor along its up axis and its distance from the world's origin (m)."""
    rows = [("camera", "size", "fx", "fy", "x", "y", "z", "distortion")
            + (("height", "from origin") if world is not None else ())]
    for c in studio:
        x, y, z = c.center
        size = f"{c.width}x{c.height}" + ("*" if c.size_guessed else "")
        row = (c.name, size, f"{c.K[0, 0]:.1f}", f"{c.K[1, 1]:.1f}",
               f"{x:.3f}", f"{y:.3f}", f"{z:.3f}", "yes" if c.has_distortion else "no")
        if world is not None:
            row += (f"{world.points_to_fit(c.center)[2]:.3f}", f"{np.linalg.norm(c.center):.3f}")
        rows.append(row)
    widths = np.max([[len(cell) for cell in row] for row in rows], axis=0)
    left = {0, 1, 7}  # text columns; numbers right-aligned
    return "\n".join("  ".join(cell.ljust(w) if i in left else cell.rjust(w)
                               for i, (cell, w) in enumerate(zip(row, widths))).rstrip()
                     for row in rows)
