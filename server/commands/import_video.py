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
out of every camera with a warning. Videos are decoded in order, never by seeking (seeking
gives grey, half-decoded frames in AVI and MP4), and their frames are counted by decoding them
(container headers can be wrong: imageio's ``count_frames`` says 426 for 214-frame AVIs). A
video's frames lost to a damaged stretch (or a gap in its timestamps) are missing frame numbers
like a folder's missing images, found from the decoded frames' times (an AVI is read again by
its index where a damaged stretch lost packets without a gap in their count); a video that lost
frames where they cannot be told (cut short, an AVI without index, its first frames) is
refused. Recordings that differ in length by at most ``MAX_TRIM_FRAMES`` frames and
``MAX_TRIM_FRACTION`` of the longest are cut to their common range with one warning; larger
differences are an error. One file given for two cameras is refused. Every source is opened,
sized and counted before the output folder is made.
"""
from __future__ import annotations

import functools
import math
import re
import shutil
import subprocess
import tempfile
from bisect import bisect_left
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image

from common.calibration import MAX_IMAGE_PIXELS, load_calibration, save_calibration, with_image_sizes
from common.errors import InputFileError, UserError, print_warning
from common.sequence import (DEFAULT_FPS, FRAME_NAME, IMAGE_SUFFIXES, check_size, expected_path, frame_files,
                             image_size, read_image, write_sequence_meta)
from common.argtypes import count, real
from server.output import add_overwrite_argument, add_units_argument, check_folder_target, staged_folder

# what an earlier import (or segment) left in a sequence folder; a calibration.json there may be
# the --calibration being imported, and is replaced by its checked copy
SEQUENCE_PARTS = ("images", "background", "silhouettes", "sequence.json")
PNG_COMPRESS_LEVEL = 1  # fast; frames are large and many
MAX_TRIM_FRAMES = 10  # recordings may differ in length by at most this many frames ...
MAX_TRIM_FRACTION = 0.05  # ... and this fraction of the longest, and are then cut to the common range
HOLD_BYTES = 1 << 30  # decoded frames kept in memory from counting to writing; beyond, a video is decoded twice
MISSING_FRAMES = ("error", "skip")  # --missing-frames: what a frame number some cameras lack is
SHOWN_FRAMES = 5  # frame numbers a message lists before "and N more"
DURATION_RESOLUTION = 0.01  # seconds: ffmpeg prints a container's duration to 10 ms
# an AVI read by its index: the frames after a damaged stretch keep their times (read in file
# order, they take those of the lost ones); no effect on other containers
INDEX_ORDER = ("-fflags", "+sortdts")
# frame periods from a video's first packet to its first decoded frame that are a decoder's delay
# where packets carry no presentation time (an Xvid AVI's B-frames: 1.5) and rounding where they
# do; more are frames lost at the start, which would shift the rest
MAX_START_DELAY = {False: Fraction(3, 2), True: Fraction(1, 2)}
NO_PTS = -(1 << 63)  # a packet without a time, as framecrc writes it


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "import-video", help="per-camera videos or image folders -> a sequence folder",
        description="Import synchronised per-camera recordings into a sequence folder: calibration.json, "
                    "sequence.json, images/<camera>/ and background/<camera>/. Each PATH is a video "
                    "file, a folder of images or one image; cameras are matched to calibration names. "
                    f"Recordings that differ in length by up to {MAX_TRIM_FRAMES} frames and "
                    f"{MAX_TRIM_FRACTION:.0%} are cut to the common range; cameras are matched by frame "
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


# --------------------------------------------------------------------------- sources
def _short(exc: Exception) -> str:
    """One line for an imageio / ffmpeg error: its first line and ffmpeg's last word on it."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    if not lines:
        return type(exc).__name__
    return lines[0] if len(lines) == 1 else f"{lines[0]}: {lines[-1]}"


def _ffmpeg(path: Path, *output: str, by_index: bool = False) -> tuple[str, str] | None:
    """ffmpeg's (stdout, stderr) reading ``path`` (an AVI in the order of its index: INDEX_ORDER)
    into the ``output`` arguments; None where it cannot run or fails."""
    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-nostdin", *(INDEX_ORDER if by_index else ()),
               "-i", str(path), *output]
    try:
        done = subprocess.run(command, capture_output=True)
    except OSError:
        return None
    if done.returncode:
        return None
    return done.stdout.decode(errors="replace"), done.stderr.decode(errors="replace")


@functools.cache
def _reports_frames() -> bool:
    """Whether ffmpeg can say which decoded frame each output frame shows (-stats_enc_pre, 6.1 on)."""
    import imageio_ffmpeg

    try:
        done = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-h", "full"], capture_output=True)
    except OSError:
        return False
    return b"-stats_enc_pre_fmt" in done.stdout


def _packets(path: Path) -> tuple[float, float, Fraction, bool] | None:
    """(seconds a video's container declares, seconds its video and audio packets span, the time
    of its first video packet, whether that is its presentation time), from its packets as read
    in file order without decoding them;
    the declared seconds are 0 where the container declares no duration or only estimates it
    from the bit rate. None where ffmpeg cannot read them. The audio counts because a
    container's duration is its longest stream's."""
    ran = _ffmpeg(path, "-map", "0:v:0", "-map", "0:a?", "-c", "copy", "-f", "framecrc", "-")
    if ran is None:
        return None
    stdout, log = ran
    time_bases, first, end, start = {}, {}, {}, None
    for line in stdout.splitlines():
        if line.startswith("#tb "):  # "#tb 0: 1/50"
            stream, base = line[4:].split(":")
            time_bases[int(stream)] = Fraction(base.strip())
        elif line and not line.startswith("#"):  # "stream, dts, pts, duration, size, crc"
            stream, dts, pts, duration = (int(v) for v in line.split(",")[:4])
            first[stream] = min(first.get(stream, dts), dts)
            end[stream] = max(end.get(stream, dts + duration), dts + duration)
            if stream == 0 and start is None:  # the video, mapped first; an AVI's packets may lack a pts
                start, dated = (dts if pts == NO_PTS else pts) * time_bases[0], pts != NO_PTS
    if start is None:
        return None
    read = max(float((end[s] - first[s]) * time_bases[s]) for s in end)
    declared = re.search(r"Duration: (\d+):(\d\d):(\d\d(?:\.\d+)?)", log)
    if declared is None or "Estimating duration from bitrate" in log:
        return 0.0, read, start, dated
    return int(declared[1]) * 3600 + int(declared[2]) * 60 + float(declared[3]), read, start, dated


def _decoded_times(path: Path, by_index: bool) -> tuple[list[Fraction], Fraction] | None:
    """(the times of the frames the decoder returns, in seconds and in order; the video's frame
    rate), decoding it as ``FrameSource._decode`` does but converting and keeping no frame; None
    where ffmpeg fails, gives no rate or a frame without a time."""
    ran = _ffmpeg(path, "-an", "-sn", "-dn", "-vf", "showinfo=checksum=0", "-f", "null", "-", by_index=by_index)
    if ran is None:
        return None
    log = ran[1]
    config = re.search(r"config in time_base: (\d+)/(\d+), frame_rate: (\d+)/(\d+)", log)
    if config is None or 0 in (int(config[2]), int(config[3]), int(config[4])):
        return None
    base, rate = Fraction(int(config[1]), int(config[2])), Fraction(int(config[3]), int(config[4]))
    try:
        times = [int(pts) * base for pts in re.findall(r"\] n: *\d+ pts: *(\S+)", log)]
    except ValueError:  # NOPTS
        return None
    return (times, rate) if times else None


def _in_step(sources: list[int], times: list[Fraction], rate: Fraction) -> dict[int, int]:
    """Frame number by output frame, for the output frames of a constant-rate decode that keep
    one, given each output frame's decoded frame (``sources``) and the decoded frames' times.

    Before the first repeated frame (an undamaged start) a frame's number is its position. At a
    gap in the decoded frames' times the output goes wrong: it repeats the frames beside the gap,
    puts the one after it early, may drop frames to catch up or stay off by the gap (an MP4's
    frame durations). From the first repeat on, a decoded frame's number is the one its time
    gives, in step with the output before the repeat (its lag: output position less the frame
    periods since the first frame); where two decoded frames get one number, the one the output
    put there wins, else the later (as the constant-rate output picks)."""
    def slot(k):
        return math.floor((times[k] - times[0]) * rate + Fraction(1, 2))

    first = next((n for n in range(1, len(sources)) if sources[n] == sources[n - 1]), len(sources))
    numbered = {n: n for n in range(first)}
    if first == len(sources):
        return numbered
    lag = (first - 1) - slot(sources[first - 1])
    last, used = first - 1, set(sources[:first])
    for n in range(first, len(sources)):
        k = sources[n]
        if k in used:
            continue
        i = slot(k) + lag
        if i == numbered[last] and numbered[last] != last:  # the later one, unless the output put the other there
            del numbered[last]
        elif i <= numbered[last]:
            continue
        numbered[n], last = i, n
        used.add(k)
    return numbered


class FrameSource:
    """Frames of one camera by source number: a folder of images (the numbers in their file
    names), one image (number 0), or a video file (a frame's position in the constant-rate decode;
    from a frame it repeats on, where frames were lost, the number the frames' times give).

    ``numbers`` (increasing) are known at once for images and after ``scan`` for a video.
    """

    def __init__(self, camera: str, path: Path, option: str):
        self.camera = camera
        self.path = path
        self.what = f"{option} {camera}"
        self.fps = None
        self.held: dict[int, np.ndarray] = {}  # source number -> frame, from scan() until written
        self.by_index = False  # a video decoded by its AVI index (see scan)
        self.numbering: dict[int, int] | None = None  # a video's frame number by position where frames were lost
        if path.is_dir():
            self.files = frame_files(path)
            if not self.files:
                raise InputFileError(path, f"{self.what}: no numbered images ({', '.join(IMAGE_SUFFIXES)}) "
                                           "in this folder")
            self.numbers = list(self.files)
        elif path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
            self.files = {0: path}
            self.numbers = [0]
        elif path.is_file():
            self.files = None
            self.numbers = None
            try:
                import imageio.v2  # noqa: F401
            except ImportError:
                raise InputFileError(path, f"{self.what}: reading video needs the imageio and imageio-ffmpeg "
                                           "packages (pip install imageio imageio-ffmpeg); or give a folder "
                                           "of images") from None
        else:
            raise InputFileError(path, f"{self.what}: does not exist")

    def where(self, number: int | None = None) -> Path:
        """The file holding frame ``number`` (None: the first frame; the video itself for a video);
        for a number a folder lacks, the file it would have."""
        if self.files is None:
            return self.path
        number = self.numbers[0] if number is None else number
        return self.files.get(number) or expected_path(self.path, self.files, number)

    def _read_file(self, number: int) -> np.ndarray:
        try:
            return read_image(self.files[number], "RGB")
        except InputFileError as exc:
            raise InputFileError(exc.path, f"{self.what}: {exc.problem}") from None

    def _decode(self, report: Path | None = None):
        """Yield the video's (H, W, 3) uint8 frames in order, at its constant frame rate (ffmpeg
        repeats or drops decoded frames to keep it); ``report``: a file where ffmpeg writes, per
        frame, the number of the decoded frame it shows."""
        import imageio.v2 as imageio
        options = {"input_params": list(INDEX_ORDER)} if self.by_index else {}
        if report is not None:
            options["output_params"] = ["-stats_enc_pre", str(report), "-stats_enc_pre_fmt", "{ni}"]
        try:
            reader = imageio.get_reader(self.path, "ffmpeg", **options)
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

    def _numbered(self):
        """Yield (frame number, frame) for a scanned video's frames in order."""
        for i, frame in enumerate(self._decode()):
            if self.numbering is None:
                yield i, frame
            elif i in self.numbering:
                yield self.numbering[i], frame

    def first(self) -> np.ndarray:
        """(H, W, 3) uint8: the first frame."""
        if self.files is not None:
            return self._read_file(self.numbers[0])
        decoded = self._decode()
        try:
            return next(decoded)
        finally:
            decoded.close()

    def scan(self, keep, hold_bytes: int, camera, whole: bool = False) -> int:
        """Number the frames (decoding a video to its end), check their size against ``camera``
        and hold those with ``keep(number)`` in memory while they fit in ``hold_bytes``; the
        rest are read again by ``frames``. Returns the bytes held. ``whole``: a video's frames
        lost to damage are left out of ``numbers``, each frame keeping its own number, and a
        video that lost frames where they cannot be told is refused."""
        used = 0
        if self.files is not None:
            for i in self.numbers:
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
        used, clock = self._scan_video(keep, hold_bytes, camera, whole)
        packets = _packets(self.path) if whole else None
        if packets is None:
            return used
        declared, read, start, dated = packets
        if clock is None and read > 0:
            rate = len(self.numbers) / read  # frames per second as decoded
            if declared - read > 1 / rate + DURATION_RESOLUTION:
                # Read in file order, a damaged stretch of an AVI loses its frames without a gap
                # in their count (packets are numbered as read), so every later frame would stand
                # in for an earlier one. Read by the AVI's index, the frames after it keep their
                # times, and the decode shows the gap.
                if _reports_frames():
                    self.by_index = True
                    self.held.clear()
                    used, clock = self._scan_video(keep, hold_bytes, camera, whole)
                if clock is None:
                    lost = max(1, round((declared - read) * rate))
                    raise InputFileError(self.path, f"{self.what}: only {read:.2f} s of the {declared:.2f} s the file "
                                                    f"declares can be read: about {lost} frames are lost (a damaged or "
                                                    "truncated file) at a place that cannot be told, so this camera "
                                                    "would fall out of step with the others (--missing-frames skip "
                                                    "cannot leave them out); repair or export the video again")
        if clock is not None and (clock[0] - start) * clock[1] > MAX_START_DELAY[dated]:
            lost = round((clock[0] - start) * clock[1])
            raise InputFileError(self.path, f"{self.what}: its first frames are lost (about {lost}; a damaged file), so "
                                            "every later frame would stand in for an earlier one (--missing-frames "
                                            "skip cannot leave them out); repair or export the video again")
        return used

    def _scan_video(self, keep, hold_bytes: int, camera, whole: bool) -> tuple[int, tuple[Fraction, Fraction] | None]:
        """``scan`` for a video: (bytes held, None or where frames were lost and left out of
        ``numbers``: the first decoded frame's time and the frame rate)."""
        used = 0
        self.numbers, self.numbering = [], None
        with tempfile.TemporaryDirectory(prefix="mocap-decode-") as folder:
            report = Path(folder) / "frames.txt" if whole and _reports_frames() else None
            for i, frame in enumerate(self._decode(report)):
                if i == 0:
                    check_size(frame.shape, self.path, camera)
                if keep(i) and used < hold_bytes:
                    self.held[i] = frame
                    used += frame.nbytes
                self.numbers.append(i)
            shown = report.read_text().split() if report is not None and report.is_file() else []
        sources = [int(k) for k in shown]
        if (len(sources) != len(self.numbers) or min(sources, default=-1) < 0
                or all(b != a for a, b in zip(sources, sources[1:]))):
            return used, None  # no decoded frame repeated: none lost (or ffmpeg does not say)
        decoded = _decoded_times(self.path, self.by_index)
        if decoded is None or max(sources) >= len(decoded[0]):
            raise InputFileError(self.path, f"{self.what}: frames are lost (a damaged file or a gap in its "
                                            "timestamps) but the times of the others cannot be read, so where they "
                                            "belong cannot be told; repair or export the video again")
        times, rate = decoded
        self.numbering = _in_step(sources, times, rate)
        self.numbers = list(self.numbering.values())
        self.held = {self.numbering[i]: frame for i, frame in self.held.items() if i in self.numbering}
        return sum(frame.nbytes for frame in self.held.values()), (times[0], rate)

    def frames(self, numbers):
        """Yield (number, (H, W, 3) uint8) for the increasing source numbers ``numbers``; frames
        held by ``scan`` are handed over (and forgotten), others read in order."""
        numbers = list(numbers)
        rest = set(numbers) - self.held.keys()
        decoded = None
        if rest and self.files is None:
            decoded = ((i, f) for i, f in self._numbered() if i in rest)
        for i in numbers:
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
    frames that the offsets put before the first synchronous one are not counted as cut; those
    of a folder that starts before the others, or of a recording that goes on after them, are.
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
    cut = max(bisect_left(f, lo) - bisect_left(f, base) + len(f) - bisect_left(f, hi) for f in frames.values())
    longest = max(len(f) - bisect_left(f, base) for f in frames.values())
    if cut > MAX_TRIM_FRAMES or cut > MAX_TRIM_FRACTION * longest:
        raise UserError(f"--video: frame counts differ between cameras: {listing()} (more than "
                        f"{MAX_TRIM_FRAMES} frames or {MAX_TRIM_FRACTION:.0%} apart; a truncated file? "
                        "a late start is --offset)")
    warning = None
    if cut:
        warning = f"recordings differ in length ({listing()} frames); using the frames {lo}..{hi - 1} all cameras have"
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


def _listed(numbers: list[int]) -> str:
    shown = ", ".join(str(n) for n in numbers[:SHOWN_FRAMES])
    return shown + (f" and {len(numbers) - SHOWN_FRAMES} more" if len(numbers) > SHOWN_FRAMES else "")


def _write_rgb(path: Path, image: np.ndarray) -> None:
    Image.fromarray(image).save(path, compress_level=PNG_COMPRESS_LEVEL)


# --------------------------------------------------------------------------- command
def run(args) -> int:
    calibration = Path(args.calibration)
    studio = load_calibration(calibration, units=args.units)
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
    studio = with_image_sizes(studio, {n: (f.shape[1], f.shape[0]) for n, f in firsts.items()}, "--video")
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
        what = f"frame {i} is" if len(lack) == 1 else f"{len(lack)} frames {_listed(lack)} are"
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
        print_warning(f"--missing-frames skip: left out of every camera: frame numbers {_listed(list(missing))} ("
                      + "; ".join(f"{n} lacks {_listed(lack)}" for n, lack in each.items() if lack) + ")")

    fps = args.fps or sources[names[0]].fps
    if fps is None:
        fps = DEFAULT_FPS
        print_warning(f"the recordings do not say their frame rate: {DEFAULT_FPS:g} fps taken (--fps sets it; "
                      "exports play at it)")
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
    print(f"imported {len(frames)} frames ({frames[0]}..{frames[-1]}) x {len(names)} cameras"
          + (" and empty-studio frames" if bg_sources else "") + f" -> {out}")
    return 0
