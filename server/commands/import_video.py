"""``mocap import-video``: per-camera videos (or image folders) -> a sequence folder.

    mocap import-video --calibration calib.json --video cam1=a.mp4 cam2=b.mp4 \\
        --background cam1=a_empty.mp4 cam2=b_empty.mp4 --out SEQUENCE [--start N --stop N --step N]

Writes ``calibration.json``, ``sequence.json``, ``images/<camera>/<frame:06d>.png`` (frame =
index in the source) and ``background/<camera>/<n:06d>.png``. A source is a video file (read
with imageio + imageio-ffmpeg when installed), a folder of images (sorted by name, numbers
in natural order) or a single image.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from PIL import Image

from common.calibration import load_calibration, save_calibration
from common.errors import InputFileError, UserError
from common.sequence import DEFAULT_FPS, FRAME_NAME, read_png, write_sequence_meta

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
PNG_COMPRESS_LEVEL = 1  # fast; frames are large and many


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "import-video", help="per-camera videos or image folders -> a sequence folder",
        description="Import synchronised per-camera recordings into a sequence folder: calibration.json, "
                    "sequence.json, images/<camera>/ and background/<camera>/. Each PATH is a video "
                    "file, a folder of images or one image; cameras are matched to calibration names.")
    parser.add_argument("--calibration", required=True, metavar="FILE", help="studio calibration")
    parser.add_argument("--video", required=True, nargs="+", action="extend", metavar="CAMERA=PATH",
                        help="recording of the actor, one per calibrated camera")
    parser.add_argument("--background", nargs="+", action="extend", default=[], metavar="CAMERA=PATH",
                        help="empty-studio recording per camera (all frames are kept)")
    parser.add_argument("--out", required=True, metavar="SEQUENCE", help="sequence folder to create")
    parser.add_argument("--start", type=int, default=0, help="first source frame (default 0)")
    parser.add_argument("--stop", type=int, default=None, help="source frame to stop before (default: all)")
    parser.add_argument("--step", type=int, default=1, help="keep every STEP-th frame (default 1)")
    parser.add_argument("--fps", type=float, default=None,
                        help="frame rate of the sources (default: from the video, else 30)")
    parser.set_defaults(func=run)


# --------------------------------------------------------------------------- sources
def _natural_key(path: Path):
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


class FrameSource:
    """Frames of one camera: a folder of images, one image, or a video file."""

    def __init__(self, camera: str, path: Path, option: str):
        self.camera = camera
        self.path = path
        self.option = option
        self.fps = None
        if path.is_dir():
            self.files = sorted((p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
            if not self.files:
                raise InputFileError(path, f"{option} {camera}: no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
            self.count = len(self.files)
        elif path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES:
            self.files = [path]
            self.count = 1
        elif path.is_file():
            self.files = None
            self._open_video()
        else:
            raise InputFileError(path, f"{option} {camera}: does not exist")

    def _open_video(self) -> None:
        try:
            import imageio.v2 as imageio
        except ImportError:
            raise InputFileError(self.path, f"{self.option} {self.camera}: reading video needs the imageio and "
                                            "imageio-ffmpeg packages (pip install imageio imageio-ffmpeg); "
                                            "or give a folder of images") from None
        try:
            reader = imageio.get_reader(self.path, "ffmpeg")
            self.count = int(reader.count_frames())
            self.fps = reader.get_meta_data().get("fps")
            reader.close()
        except Exception as exc:  # imageio raises many kinds for unreadable files
            raise InputFileError(self.path, f"{self.option} {self.camera}: not a readable video ({exc})") from None

    def where(self, index: int) -> Path:
        """The file holding frame ``index`` (the video itself for a video)."""
        return self.files[index] if self.files is not None else self.path

    def frames(self, indices: range):
        """Yield (index, (H, W, 3) uint8) for the source frames in ``indices``."""
        if self.files is not None:
            for i in indices:
                yield i, read_png(self.files[i], "RGB")
            return
        import imageio.v2 as imageio
        wanted = set(indices)
        last = max(wanted) if wanted else -1
        reader = imageio.get_reader(self.path, "ffmpeg")
        try:
            for i, frame in enumerate(reader):
                if i > last:
                    break
                if i in wanted:
                    yield i, np.ascontiguousarray(np.asarray(frame)[..., :3], dtype=np.uint8)
        finally:
            reader.close()


def _pairs(values: list[str], option: str, names: list[str], calibration: Path) -> dict[str, Path]:
    out = {}
    for value in values:
        camera, sep, path = value.partition("=")
        if not sep or not camera or not path:
            raise UserError(f"{option}: expected CAMERA=PATH, got {value!r}")
        if camera not in names:
            raise UserError(f"{option} {camera}: no camera of that name in {calibration} "
                            f"(cameras: {', '.join(names)})")
        if camera in out:
            raise UserError(f"{option} {camera}: given twice")
        out[camera] = Path(path)
    return out


def _check_size(image: np.ndarray, camera, path, index: int) -> None:
    if image.shape[:2] != (camera.height, camera.width):
        raise InputFileError(path, f"camera {camera.name}, frame {index}: size {image.shape[1]}x{image.shape[0]} "
                                   f"does not match the calibration ({camera.width}x{camera.height})")


def _write_rgb(path: Path, image: np.ndarray) -> None:
    Image.fromarray(image).save(path, compress_level=PNG_COMPRESS_LEVEL)


# --------------------------------------------------------------------------- command
def run(args) -> int:
    calibration = Path(args.calibration)
    studio = load_calibration(calibration)
    names = studio.names
    videos = _pairs(args.video, "--video", names, calibration)
    missing = [n for n in names if n not in videos]
    if missing:
        raise UserError(f"--video: no recording for camera(s) {', '.join(missing)} of {calibration}")
    backgrounds = _pairs(args.background, "--background", names, calibration)
    missing = [n for n in names if n not in backgrounds]
    if backgrounds and missing:
        raise UserError(f"--background: no empty-studio recording for camera(s) {', '.join(missing)}")
    if args.step < 1 or args.start < 0 or (args.stop is not None and args.stop < 0):
        raise UserError("--start and --stop must be >= 0 and --step >= 1")

    sources = {n: FrameSource(n, videos[n], "--video") for n in names}
    counts = {n: s.count for n, s in sources.items()}
    if len(set(counts.values())) > 1:
        raise UserError("--video: frame counts differ between cameras: "
                        + ", ".join(f"{n} {c}" for n, c in counts.items()))
    count = counts[names[0]]
    indices = range(args.start, min(count, args.stop) if args.stop is not None else count, args.step)
    if len(indices) == 0:
        raise UserError(f"--start {args.start} --stop {args.stop} --step {args.step}: no frames selected "
                        f"(the recordings have {count})")
    bg_sources = {n: FrameSource(n, p, "--background") for n, p in backgrounds.items()}
    # Check the first frame of every source before writing anything.
    for n in names:
        cam = studio.camera(n)
        for src, first in ((sources[n], indices[0]), (bg_sources.get(n), 0)):
            if src is not None:
                _, image = next(src.frames(range(first, first + 1)))
                _check_size(image, cam, src.where(first), first)

    out = Path(args.out)
    for sub in ("images", "background", "silhouettes"):
        if (out / sub).exists():
            raise InputFileError(out / sub, "already exists; import into a new sequence folder")
    out.mkdir(parents=True, exist_ok=True)
    for n in names:
        cam = studio.camera(n)
        folder = out / "images" / n
        folder.mkdir(parents=True)
        for i, image in sources[n].frames(indices):
            _check_size(image, cam, sources[n].where(i), i)
            _write_rgb(folder / FRAME_NAME.format(frame=i), image)
        if n in bg_sources:
            folder = out / "background" / n
            folder.mkdir(parents=True)
            for i, image in bg_sources[n].frames(range(bg_sources[n].count)):
                _check_size(image, cam, bg_sources[n].where(i), i)
                _write_rgb(folder / FRAME_NAME.format(frame=i), image)
    fps = args.fps or sources[names[0]].fps or DEFAULT_FPS
    save_calibration(studio, out / "calibration.json")
    write_sequence_meta(out, list(indices), float(fps), names, source={n: str(p) for n, p in videos.items()})
    print(f"imported {len(indices)} frames x {len(names)} cameras"
          + (" and empty-studio frames" if bg_sources else "") + f" -> {out}")
    return 0
