"""One camera's frames by frame number, from a video, a folder of images or one image
(``FrameSource``), for ``mocap import-video`` and ``mocap calib`` (image sizes).

A folder's frames are numbered by the numbers in their file names (``common.sequence.frame_files``),
one image is frame 0, and a video's frames by their position in a constant-rate decode, never by
seeking (seeking gives grey, half-decoded frames in AVI and MP4), counted by decoding them
(container headers can be wrong: imageio's ``count_frames`` says 426 for 214-frame AVIs). Where a
video lost frames (a damaged stretch, a gap in its timestamps) its frames from the first one the
decode repeats are numbered by their times, so the numbers the video lacks are the frames it
lost; an AVI whose damaged stretch lost packets without a gap in their count is read again by its
index. Losses whose place cannot be told (a file cut short, an AVI without an index, its first
frames) are refused.
"""
from __future__ import annotations

import functools
import math
import re
import subprocess
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

from common.calibration import MAX_IMAGE_PIXELS
from common.errors import InputFileError
from common.sequence import IMAGE_SUFFIXES, check_size, expected_path, frame_files, image_size, read_image

DURATION_RESOLUTION = 0.01  # seconds: ffmpeg prints a container's duration to 10 ms
# an AVI read by its index: the frames after a damaged stretch keep their times (read in file
# order, they take those of the lost ones); no effect on other containers
INDEX_ORDER = ("-fflags", "+sortdts")
# frame periods from a video's first packet to its first decoded frame that are a decoder's delay
# where packets carry no presentation time (an Xvid AVI's B-frames: 1.5) and rounding where they
# do; more are frames lost at the start, which would shift the rest
MAX_START_DELAY = {False: Fraction(3, 2), True: Fraction(1, 2)}
NO_PTS = -(1 << 63)  # a packet without a time, as framecrc writes it


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
