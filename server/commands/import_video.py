"""``mocap import-video``: per-camera videos (or image folders) -> a sequence folder.

    mocap import-video --calibration calib.json --video cam1=a.mp4 cam2=b.mp4 \\
        --background cam1=a_empty.mp4 cam2=b_empty.mp4 --out SEQUENCE \\
        [--start N --stop N --step N] [--offset cam2=3]

Writes ``calibration.json``, ``sequence.json``, ``images/<camera>/<frame:06d>.png`` and
``background/<camera>/<n:06d>.png``. A source is a video file (read with imageio +
imageio-ffmpeg when installed), a folder of images (ordered by the frame number in their
names, see ``common.sequence.frame_files``) or a single image.

Frame numbers are source frame indices of the cameras without an offset; ``--offset cam2=3``
says cam2's frame i + 3 was taken at the same time as the others' frame i. Videos are
decoded in order, never by seeking (seeking gives grey, half-decoded frames in AVI and MP4),
and their frames are counted by decoding them (container headers can be wrong: imageio's
``count_frames`` says 426 for 214-frame AVIs). Recordings that differ in length by at most
``MAX_TRIM_FRAMES`` frames and ``MAX_TRIM_FRACTION`` of the longest are cut to their common
range with one warning; larger differences are an error. Every source is opened, sized and
counted before the output folder is made.
"""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from common.calibration import MAX_IMAGE_PIXELS, load_calibration, save_calibration, with_image_sizes
from common.errors import InputFileError, UserError, print_warning
from common.sequence import (DEFAULT_FPS, FRAME_NAME, IMAGE_SUFFIXES, check_size, frame_files, image_size,
                             read_image, write_sequence_meta)
from common.argtypes import count, real
from server.output import add_overwrite_argument, check_folder_target, staged_folder

# what an earlier import (or segment) left in a sequence folder; a calibration.json there may be
# the --calibration being imported, and is replaced by its checked copy
SEQUENCE_PARTS = ("images", "background", "silhouettes", "sequence.json")
PNG_COMPRESS_LEVEL = 1  # fast; frames are large and many
MAX_TRIM_FRAMES = 10  # recordings may differ in length by at most this many frames ...
MAX_TRIM_FRACTION = 0.05  # ... and this fraction of the longest, and are then cut to the common range
HOLD_BYTES = 1 << 30  # decoded frames kept in memory from counting to writing; beyond, a video is decoded twice


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "import-video", help="per-camera videos or image folders -> a sequence folder",
        description="Import synchronised per-camera recordings into a sequence folder: calibration.json, "
                    "sequence.json, images/<camera>/ and background/<camera>/. Each PATH is a video "
                    "file, a folder of images or one image; cameras are matched to calibration names. "
                    f"Recordings that differ in length by up to {MAX_TRIM_FRAMES} frames and "
                    f"{MAX_TRIM_FRACTION:.0%} are cut to the common range.")
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
    add_overwrite_argument(parser)
    parser.set_defaults(func=run)


# --------------------------------------------------------------------------- sources
def _short(exc: Exception) -> str:
    """One line for an imageio / ffmpeg error: its first line and ffmpeg's last word on it."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    if not lines:
        return type(exc).__name__
    return lines[0] if len(lines) == 1 else f"{lines[0]}: {lines[-1]}"


class FrameSource:
    """Frames of one camera: a folder of images, one image, or a video file.

    ``count`` is known at once for images and after ``scan`` for a video.
    """

    def __init__(self, camera: str, path: Path, option: str):
        self.camera = camera
        self.path = path
        self.what = f"{option} {camera}"
        self.fps = None
        self.held: dict[int, np.ndarray] = {}  # source index -> frame, from scan() until written
        if path.is_dir():
            self.files = list(frame_files(path).values())
            if not self.files:
                raise InputFileError(path, f"{self.what}: no numbered images ({', '.join(IMAGE_SUFFIXES)}) "
                                           "in this folder")
            self.count = len(self.files)
        elif path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
            self.files = [path]
            self.count = 1
        elif path.is_file():
            self.files = None
            self.count = None
            try:
                import imageio.v2  # noqa: F401
            except ImportError:
                raise InputFileError(path, f"{self.what}: reading video needs the imageio and imageio-ffmpeg "
                                           "packages (pip install imageio imageio-ffmpeg); or give a folder "
                                           "of images") from None
        else:
            raise InputFileError(path, f"{self.what}: does not exist")

    def where(self, index: int) -> Path:
        """The file holding frame ``index`` (the video itself for a video)."""
        return self.files[index] if self.files is not None else self.path

    def _read_file(self, index: int) -> np.ndarray:
        try:
            return read_image(self.files[index], "RGB")
        except InputFileError as exc:
            raise InputFileError(exc.path, f"{self.what}: {exc.problem}") from None

    def _decode(self):
        """Yield the video's (H, W, 3) uint8 frames in order."""
        import imageio.v2 as imageio
        try:
            reader = imageio.get_reader(self.path, "ffmpeg")
            meta = reader.get_meta_data()
        except Exception as exc:  # imageio and ffmpeg raise many kinds for unreadable files
            raise InputFileError(self.path, f"{self.what}: not a readable video ({_short(exc)})") from None
        fps = meta.get("fps")
        # a container's rate may be missing or nonsense (0, inf): then --fps or the default decides
        self.fps = float(fps) if isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0 else None
        size = meta.get("size")
        if size and len(size) == 2 and size[0] * size[1] > MAX_IMAGE_PIXELS:  # before any frame is decoded
            raise InputFileError(self.path, f"{self.what}: frames of {size[0]}x{size[1]} pixels are over the limit "
                                            f"of {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx")
        frames = iter(reader)
        n = 0
        try:
            while True:
                try:
                    frame = next(frames)
                except StopIteration:
                    break
                except Exception as exc:
                    raise InputFileError(self.path, f"{self.what}: unreadable after frame {n} "
                                                    f"({_short(exc)}); truncated?") from None
                yield np.ascontiguousarray(np.asarray(frame)[..., :3], dtype=np.uint8)
                n += 1
        finally:
            reader.close()
        if n == 0:
            raise InputFileError(self.path, f"{self.what}: a video without frames (truncated?)")

    def first(self) -> np.ndarray:
        """(H, W, 3) uint8: the first frame."""
        if self.files is not None:
            return self._read_file(0)
        decoded = self._decode()
        try:
            return next(decoded)
        finally:
            decoded.close()

    def scan(self, keep, hold_bytes: int, camera) -> int:
        """Count the frames (decoding a video to its end), check their size against ``camera``
        and hold those with ``keep(index)`` in memory while they fit in ``hold_bytes``; the
        rest are read again by ``frames``. Returns the bytes held."""
        used = 0
        if self.files is not None:
            for i in range(self.count):
                if not keep(i):
                    continue
                if used < hold_bytes:
                    frame = self._read_file(i)
                    check_size(frame.shape, self.where(i), camera)
                    self.held[i] = frame
                    used += frame.nbytes
                else:  # read again when written: its header is checked now
                    width, height = image_size(self.where(i))
                    check_size((height, width), self.where(i), camera)
            return used
        count = 0
        for i, frame in enumerate(self._decode()):
            if i == 0:
                check_size(frame.shape, self.path, camera)
            if keep(i) and used < hold_bytes:
                self.held[i] = frame
                used += frame.nbytes
            count = i + 1
        self.count = count
        return used

    def frames(self, indices):
        """Yield (index, (H, W, 3) uint8) for the increasing source indices ``indices``; frames
        held by ``scan`` are handed over (and forgotten), others read in order."""
        indices = list(indices)
        rest = set(indices) - self.held.keys()
        decoded = None
        if rest and self.files is None:
            decoded = ((i, f) for i, f in enumerate(self._decode()) if i in rest)
        for i in indices:
            if i in self.held:
                yield i, self.held.pop(i)
            elif decoded is None:
                yield i, self._read_file(i)
            else:
                j, frame = next(decoded, (None, None))
                if j != i:
                    raise InputFileError(self.path, f"{self.what}: frame {i} is missing when decoded again "
                                                    "(did the file change?)")
                yield i, frame


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
    """The first frame number every camera has (camera c's frame number i is its source frame i + offset_c)."""
    return max(0, *(-o for o in offsets.values()))


def _common_range(counts: dict[str, int], offsets: dict[str, int]) -> tuple[int, int, str | None]:
    """[lo, hi) frame numbers every camera has, and the warning when lengths were cut."""
    lo = _first_frame(offsets)
    lengths = {n: counts[n] - offsets[n] - lo for n in counts}
    shortest, longest = min(lengths.values()), max(lengths.values())

    def listing():
        return ", ".join(f"{n} {counts[n]}" + (f" (offset {offsets[n]:+d})" if offsets[n] else "") for n in counts)

    if shortest <= 0:
        raise UserError(f"--offset: the recordings have no frames in common ({listing()} frames)")
    difference = longest - shortest
    if difference > MAX_TRIM_FRAMES or difference > MAX_TRIM_FRACTION * longest:
        raise UserError(f"--video: frame counts differ between cameras: {listing()} (more than "
                        f"{MAX_TRIM_FRAMES} frames or {MAX_TRIM_FRACTION:.0%} apart; a truncated file? "
                        "a late start is --offset)")
    hi = lo + shortest
    warning = None
    if difference:
        warning = (f"recordings differ in length ({listing()} frames); using the {shortest} frames "
                   f"{lo}..{hi - 1} all cameras have")
    return lo, hi, warning


def _write_rgb(path: Path, image: np.ndarray) -> None:
    Image.fromarray(image).save(path, compress_level=PNG_COMPRESS_LEVEL)


# --------------------------------------------------------------------------- command
def run(args) -> int:
    calibration = Path(args.calibration)
    studio = load_calibration(calibration)
    names = studio.names
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

    # Every source is opened, sized and counted before anything is written.
    sources = {n: FrameSource(n, videos[n], "--video") for n in names}
    bg_sources = {n: FrameSource(n, p, "--background") for n, p in backgrounds.items()}
    firsts = {n: s.first() for n, s in sources.items()}
    # A calibration without image sizes gets the videos'; one with sizes must agree with them.
    studio = with_image_sizes(studio, {n: (f.shape[1], f.shape[0]) for n, f in firsts.items()}, "--video")
    for n, src in bg_sources.items():
        check_size(src.first().shape, src.where(0), studio.camera(n))

    begin = max(args.start, _first_frame(offsets))
    begin += -(begin - args.start) % args.step  # stay on the --start + k --step grid

    def keeper(offset):
        return lambda j: j - offset >= begin and (j - offset - begin) % args.step == 0 and (
            args.stop is None or j - offset < args.stop)

    hold = HOLD_BYTES
    for n in names:
        hold -= sources[n].scan(keeper(offsets[n]), hold, studio.camera(n))
    for n, src in bg_sources.items():
        hold -= src.scan(lambda j: True, hold, studio.camera(n))
    counts = {n: sources[n].count for n in names}
    lo, hi, warning = _common_range(counts, offsets)
    frames = range(begin, hi if args.stop is None else min(hi, args.stop), args.step)
    if len(frames) == 0:
        stop = "" if args.stop is None else f" --stop {args.stop}"
        raise UserError(f"--start {args.start}{stop} --step {args.step}: no frames selected "
                        f"(the recordings have frames {lo}..{hi - 1} in common)")
    if warning:
        print_warning(warning)

    fps = args.fps or sources[names[0]].fps or DEFAULT_FPS
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
                for j, image in bg_sources[n].frames(range(bg_sources[n].count)):
                    check_size(image.shape, bg_sources[n].where(j), cam)
                    _write_rgb(folder / FRAME_NAME.format(frame=j), image)
        save_calibration(studio, staged / "calibration.json")
        extra = {"source": {n: str(p) for n, p in videos.items()}}
        if any(offsets.values()):
            extra["offsets"] = offsets
        write_sequence_meta(staged, list(frames), float(fps), names, **extra)
    if args.overwrite:  # silhouettes of the images just replaced
        shutil.rmtree(out / "silhouettes", ignore_errors=True)
    print(f"imported {len(frames)} frames ({frames[0]}..{frames[-1]}) x {len(names)} cameras"
          + (" and empty-studio frames" if bg_sources else "") + f" -> {out}")
    return 0
