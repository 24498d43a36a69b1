"""``mocap import-video``: per-camera videos (or image folders) -> a sequence folder.

    mocap import-video --calibration calib.json --video cam1=a.mp4 cam2=b.mp4 \\
        --background cam1=a_empty.mp4 cam2=b_empty.mp4 --out SEQUENCE \\
        [--start N --stop N --step N] [--offset cam2=3] [--units mm] [--missing-frames skip]

Writes ``calibration.json``, ``sequence.json``, ``images/<camera>/<frame:06d>.png`` and
``background/<camera>/<n:06d>.png``. A source is a video file (read with imageio +
imageio-ffmpeg when installed), a folder of images (ordered by the frame number in their
names, see ``common.sequence.frame_files``) or a single image.

Frame numbers are the sources' own: a video frame's position, the number in an image's file
name (0 for a single image); ``--offset cam2=3`` says cam2's frame i + 3 was taken at the same
time as the others' frame i. Cameras are matched by frame number, so a frame one folder lacks
cannot shift the frames after it: a frame number inside the cameras' common range that some
have and others lack is an error naming the file, or with ``--missing-frames skip`` is left
out of every camera with a warning. A video's frames lost to a damaged stretch (or a gap in its
timestamps) are missing frame numbers like a folder's missing images (how a video is read and
its lost frames found: ``server.frame_sources``). Recordings that differ in length by at most ``MAX_TRIM_FRAMES`` frames and
``MAX_TRIM_FRACTION`` of the longest (or by ``FEW_FRAMES`` whatever the length) are cut to their
common range with one warning; larger differences are an error. One file given for two cameras is refused. Every source is opened,
sized and counted before the output folder is made.
"""
from __future__ import annotations

import shutil
from bisect import bisect_left
from pathlib import Path

import numpy as np
from PIL import Image

from common.calibration import load_calibration, save_calibration
from common.errors import InputFileError, UserError, print_warning
from common.sequence import DEFAULT_FPS, FRAME_NAME, check_size, write_sequence_meta
from common.argtypes import count, real
from server.frame_sources import FrameSource
from server.output import (add_overwrite_argument, add_units_argument, check_folder_target, counted, listed,
                           staged_folder)

# what an earlier import (or segment) left in a sequence folder; a calibration.json there may be
# the --calibration being imported, and is replaced by its checked copy
SEQUENCE_PARTS = ("images", "background", "silhouettes", "sequence.json")
PNG_COMPRESS_LEVEL = 1  # fast; frames are large and many
MAX_TRIM_FRAMES = 10  # recordings may differ in length by at most this many frames ...
MAX_TRIM_FRACTION = 0.05  # ... and this fraction of the longest, and are then cut to the common range;
FEW_FRAMES = 3  # this many always (a short take's cameras stopped a frame or two apart)
HOLD_BYTES = 1 << 30  # decoded frames kept in memory from counting to writing; beyond, a video is decoded twice
MISSING_FRAMES = ("error", "skip")  # --missing-frames: what a frame number some cameras lack is


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "import-video", help="per-camera videos or image folders -> a sequence folder",
        description="Import synchronised per-camera recordings into a sequence folder: calibration.json, "
                    "sequence.json, images/<camera>/ and background/<camera>/. Each PATH is a video "
                    "file, a folder of images or one image; cameras are matched to calibration names. "
                    f"Recordings that differ in length by up to {MAX_TRIM_FRAMES} frames and "
                    f"{MAX_TRIM_FRACTION:.0%} (or {FEW_FRAMES} frames) are cut to the common range; cameras are "
                    "matched by frame "
                    "number (an image's file name, a video frame's position).")
    parser.add_argument("--calibration", required=True, metavar="FILE", help="studio calibration")
    parser.add_argument("--video", required=True, nargs="+", action="extend", metavar="CAMERA=PATH",
                        help="recording of the actor, one per calibrated camera")
    parser.add_argument("--background", nargs="+", action="extend", default=[], metavar="CAMERA=PATH",
                        help="empty-studio recording per camera (all frames are kept)")
    parser.add_argument("--out", required=True, metavar="SEQUENCE", help="sequence folder to create")
    parser.add_argument("--start", type=count(0), default=0, help="first frame (default 0)")
    parser.add_argument("--stop", type=count(0), default=None, help="frame to stop before (default: all)")
    parser.add_argument("--step", type=count(1), default=1, help="keep every STEP-th frame (default 1)")
    parser.add_argument("--offset", nargs="+", action="extend", default=[], metavar="CAMERA=FRAMES",
                        help="CAMERA's frame i + FRAMES is synchronous with the other cameras' frame i "
                             "(FRAMES may be negative; default 0)")
    parser.add_argument("--fps", type=real(0.0, exclusive_minimum=True), default=None,
                        help="frame rate of the sources (default: from the video, else 30)")
    parser.add_argument("--missing-frames", choices=MISSING_FRAMES, default="error",
                        help="a frame number that some cameras have and others lack (an image missing from a "
                             "folder, frames a damaged video lost): error (default), or skip: leave it out of "
                             "every camera, with a warning")
    add_units_argument(parser)
    add_overwrite_argument(parser)
    parser.set_defaults(func=run)


def _one_camera_per_file(sources: list[FrameSource]) -> None:
    """Refuse a file or folder given for two cameras (a link to it is the same file): two cameras
    cannot record the same file."""
    seen: dict[tuple[int, int], FrameSource] = {}
    for src in sources:
        status = src.path.stat()
        earlier = seen.setdefault((status.st_dev, status.st_ino), src)
        if earlier.camera != src.camera:
            kind = "folder" if src.path.is_dir() else "file"
            raise InputFileError(src.path, f"given for both {earlier.what} and {src.what}: two cameras cannot "
                                           f"record the same {kind}")


# --------------------------------------------------------------------------- options
def _pairs(values: list[str], option: str, names: list[str], calibration: Path, what: str = "PATH") -> dict[str, str]:
    out = {}
    for value in values:
        camera, sep, text = value.partition("=")
        if not sep or not camera or not text:
            raise UserError(f"{option}: expected CAMERA={what}, got {value!r}")
        if camera not in names:
            raise UserError(f"{option} {camera}: no camera of that name in {calibration} "
                            f"(cameras: {', '.join(names)})")
        if camera in out:
            raise UserError(f"{option} {camera}: given twice")
        out[camera] = text
    return out


def _offsets(values: list[str], names: list[str], calibration: Path) -> dict[str, int]:
    """Frame offset per camera (0 for those not given)."""
    out = dict.fromkeys(names, 0)
    for camera, text in _pairs(values, "--offset", names, calibration, "FRAMES").items():
        try:
            out[camera] = int(text)
        except ValueError:
            raise UserError(f"--offset {camera}: expected a whole number of frames, got {text!r}") from None
    return out


def _first_frame(offsets: dict[str, int]) -> int:
    """The first frame number every camera has were each source numbered from 0 (camera c's frame
    number i is its source number i + offset_c)."""
    return max(0, *(-o for o in offsets.values()))


def _common_range(frames: dict[str, list[int]], offsets: dict[str, int]) -> tuple[int, int, str | None]:
    """[lo, hi) frame numbers every camera spans, and the warning when frames were cut.

    frames: each camera's frame numbers (its source numbers less its offset), increasing. The
    frames that the offsets put before the first synchronous one, or after the last, are not
    counted as cut, whatever numbers the sources start from; those of a folder that starts
    before the others, or of a recording that goes on after them, are.
    """
    base = _first_frame(offsets)
    lo = max(base, *(f[0] for f in frames.values()))
    hi = min(f[-1] for f in frames.values()) + 1

    def listing():
        def numbered(n, f):  # a folder's own numbers where they do not run 0..count-1
            first, last = f[0] + offsets[n], f[-1] + offsets[n]
            return f" numbered {first}..{last}" if (first, last) != (0, len(f) - 1) else ""
        return ", ".join(f"{n} {len(f)}" + numbered(n, f) + (f" (offset {offsets[n]:+d})" if offsets[n] else "")
                         for n, f in frames.items())

    if hi <= lo:
        raise UserError(f"--offset: the recordings have no frames in common ({listing()} frames)")
    # the frames each camera has before the others' first and after their last; an offset puts a
    # camera's frames that many later (earlier) against the others', and what that cuts is the
    # offset's doing, not a recording that differs
    latest_start = max(f[0] for f in frames.values())
    ends = {n: (bisect_left(f, latest_start), len(f) - bisect_left(f, hi)) for n, f in frames.items()}
    low, high = min(offsets.values()), max(offsets.values())
    cut = max(max(0, start - (offsets[n] - low)) + max(0, end - (high - offsets[n]))
              for n, (start, end) in ends.items())
    longest = max(len(f) - bisect_left(f, base) for f in frames.values())
    if cut > MAX_TRIM_FRAMES or (cut > FEW_FRAMES and cut > MAX_TRIM_FRACTION * longest):
        raise UserError(f"--video: frame counts differ between cameras: {listing()} (more than "
                        f"{MAX_TRIM_FRAMES} frames, or more than {FEW_FRAMES} and {MAX_TRIM_FRACTION:.0%} apart; "
                        "a truncated file? a late start is --offset: a first guess, and mocap sync finds the rest)")
    warning = None
    if cut:
        warning = (f"recordings differ in length ({listing()} frames); all cameras have the frames {lo}..{hi - 1}, "
                   f"the rest is left out (a camera that started late is out of step: mocap sync finds its "
                   f"--offset)")
    elif any(end for _, end in ends.values()):
        warning = f"with the offsets ({listing()} frames) the frames all cameras have are {lo}..{hi - 1}"
    return lo, hi, warning


def _on_grid(first: int, start: int, step: int) -> int:
    """The first frame number from ``first`` on, and from ``start`` on, on the --start + k --step grid."""
    begin = max(first, start)
    return begin + -(begin - start) % step


def _lacking(numbered: dict[str, list[int]], wanted: range) -> dict[int, list[str]]:
    """The frame numbers in ``wanted`` that some camera has, each with the cameras that lack it
    (an empty list where all have it). A number no camera has is no frame (folders numbered in
    steps)."""
    have = {n: set(f) for n, f in numbered.items()}
    out = {}
    for i in wanted:
        lack = [n for n, h in have.items() if i not in h]
        if len(lack) < len(have):
            out[i] = lack
    return out


def _write_rgb(path: Path, image: np.ndarray) -> None:
    Image.fromarray(image).save(path, compress_level=PNG_COMPRESS_LEVEL)


# --------------------------------------------------------------------------- command
def run(args) -> int:
    calibration = Path(args.calibration)
    # read quietly for its cameras; its warnings come once the videos have given the sizes
    names = load_calibration(calibration, units=args.units, warn=lambda line: None).names
    videos = {n: Path(p) for n, p in _pairs(args.video, "--video", names, calibration).items()}
    missing = [n for n in names if n not in videos]
    if missing:
        raise UserError(f"--video: no recording for camera(s) {', '.join(missing)} of {calibration}")
    backgrounds = {n: Path(p) for n, p in _pairs(args.background, "--background", names, calibration).items()}
    missing = [n for n in names if n not in backgrounds]
    if backgrounds and missing:
        raise UserError(f"--background: no empty-studio recording for camera(s) {', '.join(missing)}")
    offsets = _offsets(args.offset, names, calibration)
    out = Path(args.out)
    check_folder_target(out, SEQUENCE_PARTS, overwrite=args.overwrite, what="sequence")
    for option, given in (("--video", videos), ("--background", backgrounds)):
        for n, source in given.items():  # --overwrite would replace the recording's own frames
            if source.is_dir() and out.resolve().is_relative_to(source.resolve()):
                raise UserError(f"--out {out}: inside {option} {n}'s folder {source}; choose a folder outside it")

    # Every source is opened, sized and counted before anything is written.
    sources = {n: FrameSource(n, videos[n], "--video") for n in names}
    bg_sources = {n: FrameSource(n, p, "--background") for n, p in backgrounds.items()}
    _one_camera_per_file([*sources.values(), *bg_sources.values()])
    firsts = {n: s.first() for n, s in sources.items()}
    # A calibration without image sizes gets the videos'; one with sizes must agree with them.
    studio = load_calibration(calibration, units=args.units, images="--video",
                              image_sizes={n: (f.shape[1], f.shape[0]) for n, f in firsts.items()})
    for n, src in bg_sources.items():
        check_size(src.first().shape, src.where(), studio.camera(n))

    begin = _on_grid(_first_frame(offsets), args.start, args.step)

    def keeper(offset):
        return lambda j: j - offset >= begin and (j - offset - begin) % args.step == 0 and (
            args.stop is None or j - offset < args.stop)

    hold = HOLD_BYTES
    for n in names:
        hold -= sources[n].scan(keeper(offsets[n]), hold, studio.camera(n), whole=True)
    for n, src in bg_sources.items():
        hold -= src.scan(lambda j: True, hold, studio.camera(n))
    numbered = {n: [j - offsets[n] for j in sources[n].numbers] for n in names}
    lo, hi, warning = _common_range(numbered, offsets)
    wanted = range(_on_grid(lo, args.start, args.step), hi if args.stop is None else min(hi, args.stop), args.step)
    lacking = _lacking(numbered, wanted)
    missing = {i: cams for i, cams in lacking.items() if cams}
    if missing and args.missing_frames == "error":
        i, cams = next(iter(missing.items()))
        src = sources[cams[0]]
        lack = [j for j, c in missing.items() if src.camera in c]
        others = ", ".join(n for n in names if n not in cams)
        more = len(missing) - len(lack)
        more = f"; {more} more frame numbers lack some camera's image" if more else ""
        what = f"frame {i} is" if len(lack) == 1 else f"{len(lack)} frames {listed(lack)} are"
        # a video lacks the frames a damaged stretch lost; a folder, files
        how = "missing here" if src.files is not None else "lost (a damaged stretch, or a gap in its timestamps)"
        raise InputFileError(src.where(i + offsets[src.camera]),
                             f"{src.what}: {what} {how} but not in {others}{more} "
                             "(--missing-frames skip leaves such frames out of every camera)")
    frames = [i for i, cams in lacking.items() if not cams]
    if not frames:
        stop = "" if args.stop is None else f" --stop {args.stop}"
        raise UserError(f"--start {args.start}{stop} --step {args.step}: no frames selected "
                        f"(the recordings have frames {lo}..{hi - 1} in common)")
    if warning:
        print_warning(warning)
    if missing:
        each = {n: [i for i, cams in missing.items() if n in cams] for n in names}
        print_warning(f"--missing-frames skip: left out of every camera: frame numbers {listed(list(missing))} ("
                      + "; ".join(f"{n} lacks {listed(lack)}" for n, lack in each.items() if lack) + ")")

    fps = args.fps or sources[names[0]].fps
    if fps is None:
        fps = DEFAULT_FPS
        print_warning(f"the recordings do not say their frame rate: {DEFAULT_FPS:g} fps taken (--fps sets it, "
                      "[import] fps in a project's Config.toml; exports play at it)")
    # the whole sequence is built beside OUT and moved in at the end: a failed import leaves OUT as it was
    with staged_folder(out, merge=True) as staged:
        for n in names:
            cam = studio.camera(n)
            folder = staged / "images" / n
            folder.mkdir(parents=True)
            for j, image in sources[n].frames(i + offsets[n] for i in frames):
                check_size(image.shape, sources[n].where(j), cam)
                _write_rgb(folder / FRAME_NAME.format(frame=j - offsets[n]), image)
            sources[n].held.clear()  # frames past the common range
            if n in bg_sources:
                folder = staged / "background" / n
                folder.mkdir(parents=True)
                for j, image in bg_sources[n].frames(bg_sources[n].numbers):
                    check_size(image.shape, bg_sources[n].where(j), cam)
                    _write_rgb(folder / FRAME_NAME.format(frame=j), image)
        save_calibration(studio, staged / "calibration.json")
        extra = {"source": {n: str(p) for n, p in videos.items()}}
        if any(offsets.values()):
            extra["offsets"] = offsets
        write_sequence_meta(staged, frames, float(fps), names, **extra)
    if args.overwrite:  # silhouettes of the images just replaced
        shutil.rmtree(out / "silhouettes", ignore_errors=True)
    print(f"imported {counted(len(frames), 'frame')} ({frames[0]}..{frames[-1]}) x {counted(len(names), 'camera')}"
          + (" and empty-studio frames" if bg_sources else "") + f" -> {out}")
    return 0
