"""Sequence folders: calibration, per-camera silhouettes or images, optional ground truth.

Layout (see docs/CONTRIBUTING.md)::

    SEQUENCE/calibration.json                     (or EasyMocap's intri.yml + extri.yml; not both;
                                                   or a calibration file given, ``calibration``)
    SEQUENCE/sequence.json                        {"frames": [...], "fps": 30.0, "cameras": [...]}
    SEQUENCE/silhouettes/<camera>/<frame:06d>.png (or EasyMocap / ZJU-MoCap mask/ or masks/)
    SEQUENCE/images/<camera>/<frame:06d>.png
    SEQUENCE/background/<camera>/<n:06d>.png
    SEQUENCE/truth.jsonl

Frame files may be PNG, JPEG, BMP, PBM/PGM/PPM or TIFF under any name: the frame number is
the run of digits that differs in every file of a camera's folder (``frame_run``), else the
last run of digits in the name (``img_2.jpg`` -> 2, ``000010.png`` -> 10).

Cameras may differ in resolution. Per-frame stacks are then padded: ``silhouettes(frame)``
is ``(K, Hmax, Wmax)`` bool and ``images(frame)`` ``(K, Hmax, Wmax, 3)`` uint8, with camera
k's pixels in ``[k, :h_k, :w_k]`` and False / 0 elsewhere (Hmax, Wmax: the largest height
and width of the studio's cameras, ``Sequence.padded_shape``; the convention of
``common.packing.pad_stack``).

The world: ``Sequence.user_studio`` is the calibration as the file has it; ``Sequence.studio``
the same cameras in the z-up fit frame (``common.world``; ``up`` "auto" detects the file's up
axis), which every fit, voxel and picture uses; ``Sequence.world`` turns points back.
``silhouettes`` drops the blobs that the other cameras do not support (``clean_masks``; see
``common.consistency``); ``raw_silhouettes`` reads the files as they are.
"""
from __future__ import annotations

import copy
import json
import re
import threading
import warnings
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from common.body import JOINT_NAMES, PARAM_NAMES
from common.calibration import EASYMOCAP_FILES, MAX_IMAGE_PIXELS, load_calibration, natural_key, refuse_calibrations
from common.camera import Studio
from common.consistency import PROP_SAMPLES, StaticProps, static_props, supported_masks
from common.errors import FieldChecks, InputFileError, UserError, print_warning
from common.packing import pad_stack
from common.voxels import silhouette_centre
from common.world import WorldFrame, below_floor_warning, resolve_world

FRAME_NAME = "{frame:06d}.png"  # how we write frames
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pbm", ".pgm", ".ppm", ".pnm", ".tif", ".tiff")
MASK_FOLDERS = ("silhouettes", "mask", "masks")  # ours first, then EasyMocap / ZJU-MoCap's
IMAGE_FOLDER = "images"
DEFAULT_FPS = 30.0  # frames per second when sequence.json does not say
MAX_MASK_THRESHOLD = 65535  # grey levels of 16-bit masks
WIDE_MODES = ("I", "I;16", "I;16B", "I;16L", "F")  # PIL's modes of grey masks wider than 8 bits
# bytes of cleaned masks a Sequence keeps, bit-packed (77 kB a frame at 8 x 320x240: 800 frames):
# a fit reads each frame at least three times (tracking, refinement, the fit-quality record),
# and cleaning one costs tens of milliseconds, unpacking it a fraction of one
CLEANED_BYTES_KEPT = 64 * 1024 * 1024

_DIGITS = re.compile(r"\d+")
# What PIL raises for a file that is not a readable image: truncated or corrupt data ends in
# OSError, ValueError or SyntaxError (a broken PNG chunk) or EOFError, depending on the format.
IMAGE_ERRORS = (UnidentifiedImageError, OSError, ValueError, SyntaxError, EOFError)
# Every image is checked against MAX_IMAGE_PIXELS on its header, before a pixel is decoded
# (_open_image); PIL's own guard (a warning, then DecompressionBombError at twice its limit)
# would name neither the size nor the limit, so it is off.
Image.MAX_IMAGE_PIXELS = None


@dataclass(frozen=True)
class TruthFrame:
    frame: int
    params: np.ndarray  # (35,)
    joints: dict  # name -> (3,) metres


# --------------------------------------------------------------------------- files
def frame_run(stems: list[str]) -> int:
    """Which run of digits numbers the frames of one folder's file names (stems), as an index
    into each name's runs, where every name has as many runs: of the runs that differ in every
    file, the one numbered most densely (the smallest largest gap between its sorted values: a
    frame counter steps by one or by the import's step, a time stamp by a frame's duration);
    "0001_c1" -> the first; ZJU-MoCap's "CoreView_313_Camera_(1)_0001_2019-08-23_16-08-50.592"
    -> the fourth, not the milliseconds. Else the last run (-1), as for a name taken alone
    ("img_2" -> 2)."""
    runs = np.array([[int(r) for r in _DIGITS.findall(stem)] for stem in stems], dtype=object)
    if len(stems) < 2 or runs.ndim != 2 or runs.shape[1] == 0:  # ragged: names of different shapes
        return -1
    distinct = [k for k in range(runs.shape[1]) if len(set(runs[:, k])) == len(stems)]
    if not distinct:
        return -1
    return min(distinct, key=lambda k: (max(np.diff(sorted(runs[:, k]))), k))


def frame_files(folder) -> dict[int, Path]:
    """Frame number -> image file of one camera's folder, in frame order (empty if no folder).

    Every file with an image suffix (``IMAGE_SUFFIXES``, any case) and a digit in its name
    counts; its frame number is the run of digits ``frame_run`` picks for the folder. Two files
    with the same number are refused.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return {}
    paths = [path for path in sorted(folder.iterdir(), key=lambda p: natural_key(p.name))
             if path.suffix.lower() in IMAGE_SUFFIXES and not path.name.startswith(".")
             and _DIGITS.search(path.stem)]
    k = frame_run([path.stem for path in paths])
    found: dict[int, Path] = {}
    for path in paths:
        number = int(_DIGITS.findall(path.stem)[k])
        if number in found:
            raise InputFileError(folder, f"two files for frame {number}: {found[number].name} and {path.name}")
        found[number] = path
    return dict(sorted(found.items()))


def expected_path(folder: Path, files: dict[int, Path], frame: int) -> Path:
    """The file frame ``frame`` would have, named like its neighbours (for 'missing' errors)."""
    if not files:
        return folder / FRAME_NAME.format(frame=frame)
    example = next(iter(files.values()))
    stem = example.stem
    digits = list(_DIGITS.finditer(stem))[frame_run([p.stem for p in files.values()])]
    number = str(frame).zfill(len(digits.group()))
    return folder / f"{stem[:digits.start()]}{number}{stem[digits.end():]}{example.suffix}"


@contextmanager
def _open_image(path):
    """An image file opened on its header, for reading in the ``with`` block; a missing file, a
    folder, a file that is not a readable image (also when its pixels are decoded in the block)
    and one of more than MAX_IMAGE_PIXELS are each one InputFileError."""
    if Path(path).is_dir():
        raise InputFileError(path, "a folder, expected an image file")
    try:
        with warnings.catch_warnings():
            # PIL warns (lines on stderr) of tags it skips in a damaged file; it reads or fails as it can
            warnings.simplefilter("ignore")
            with Image.open(path) as im:
                width, height = im.size
                if width * height > MAX_IMAGE_PIXELS:
                    raise InputFileError(path, f"declares {width}x{height} pixels, more than the "
                                               f"{MAX_IMAGE_PIXELS / 1e6:g} Mpx an image may have")
                yield im
    except FileNotFoundError:
        raise InputFileError(path, "missing") from None
    except IMAGE_ERRORS as exc:
        # PIL's messages may hold line breaks, and name the file the error line names already
        reason = " ".join(str(exc).replace(repr(str(path)), "").replace(str(path), "").split()) or type(exc).__name__
        raise InputFileError(path, f"not a readable image ({reason})") from None


def read_image(path, mode: str) -> np.ndarray:
    """Read one image of any PIL format ('L' -> (H, W) uint8, 'RGB' -> (H, W, 3) uint8)."""
    with _open_image(path) as im:
        return np.asarray(im.convert(mode))


def image_size(path) -> tuple[int, int]:
    """(width, height) of an image file from its header (the pixels are not decoded)."""
    with _open_image(path) as im:
        return im.size


def read_mask(path, threshold: int | None = None) -> np.ndarray:
    """Read one silhouette as (H, W) bool.

    Without a threshold the file must be binary: at most two grey levels (the higher is
    silhouette; a single level is silhouette when non-zero). Colour images (channels that
    differ) and grey images with more levels are refused, but for a palette image of black and
    one colour (a label map), whose colour is silhouette. With a threshold, grey
    level > threshold is silhouette (colour is converted to grey first); a threshold that
    leaves no level of an 8-bit image above it is refused.
    """
    with _open_image(path) as im:
        if im.mode == "1":
            return np.asarray(im, dtype=bool)
        eight_bit = im.mode not in WIDE_MODES
        if im.mode in ("L", *WIDE_MODES):
            grey, colour = np.asarray(im), False
        elif im.mode in ("LA", "La"):
            grey, colour = np.asarray(im.getchannel(0)), False
        else:
            rgb = np.asarray(im.convert("RGB"))
            colour = not (np.array_equal(rgb[..., 0], rgb[..., 1]) and np.array_equal(rgb[..., 0], rgb[..., 2]))
            grey = np.asarray(im.convert("L")) if colour else rgb[..., 0]
            if colour and threshold is None and im.mode in ("P", "PA"):
                # a palette image of black and one colour is a label map (the background and the
                # person's label, as segmentation tools write them)
                packed = rgb[..., 0].astype(np.uint32) << 16 | rgb[..., 1].astype(np.uint32) << 8 | rgb[..., 2]
                shown = np.unique(packed)
                if len(shown) == 2 and shown[0] == 0:  # black and a colour (np.unique sorts: black first)
                    return packed == shown[1]
    if threshold is not None:
        if eight_bit and threshold >= 255:
            raise InputFileError(path, f"an 8-bit image: no grey level is above the mask threshold {threshold} "
                                       "(0..254 for 8-bit masks)")
        return grey > threshold
    hint = "give binary masks, or a mask threshold (--mask-threshold N: grey level > N is silhouette)"
    if colour:
        raise InputFileError(path, f"a colour image, not a mask (its red, green and blue differ); {hint}")
    lo, hi = grey.min(), grey.max()
    if lo == hi:
        return np.full(grey.shape, bool(hi > 0))
    if not np.all((grey == lo) | (grey == hi)):
        raise InputFileError(path, f"a grey image, not a mask (more than two grey levels, {lo}..{hi}); {hint}")
    return grey > lo


def write_mask_png(path: Path, mask: np.ndarray) -> None:
    """(H, W) bool -> 1-bit PNG (compact, lossless)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(mask, dtype=bool)).save(path, optimize=False)


def check_size(shape: tuple, path: Path, cam) -> None:
    """Refuse an image of array shape (h, w, ...) whose size is not its camera's."""
    if tuple(shape[:2]) != (cam.height, cam.width):
        raise InputFileError(path, f"size {shape[1]}x{shape[0]} does not match the "
                                   f"calibration of {cam.name} ({cam.width}x{cam.height})")


# --------------------------------------------------------------------------- sequence
class Sequence:
    """A sequence folder opened for reading.

    mask_threshold: None to accept only binary masks, else grey level > threshold is silhouette.
    calibration: a calibration file (any format) or EasyMocap folder to use instead of the
    sequence's own (a project's, for a sequence that holds none); None: the sequence's own.
    """

    def __init__(self, path, units: str | None = None, mask_threshold: int | None = None, up: str = "auto",
                 clean_masks: bool = True, calibration=None):
        self.path = Path(path)
        if not self.path.is_dir():
            raise InputFileError(self.path, "not a sequence folder (does not exist)")
        if mask_threshold is not None and (isinstance(mask_threshold, bool) or not isinstance(mask_threshold, int)
                                           or not 0 <= mask_threshold < MAX_MASK_THRESHOLD):
            raise UserError(f"mask threshold: expected a whole grey level 0..{MAX_MASK_THRESHOLD - 1}, "
                            f"got {mask_threshold!r}")
        self.mask_threshold = mask_threshold
        # a calibration given (a project's, for sequences that hold none) is read in any format
        self.calibration = Path(calibration) if calibration is not None else None
        own = self.path / "calibration.json"
        easymocap = all((self.path / n).is_file() for n in EASYMOCAP_FILES)
        if easymocap and own.exists() and self.calibration is None:
            refuse_calibrations(self.path, [own.name, " + ".join(EASYMOCAP_FILES)], "keep one")
        source, fmt = ((self.calibration, None) if self.calibration is not None
                       else (self.path, "easymocap") if easymocap else (own, None))
        self.mask_folder = next((self.path / f for f in MASK_FOLDERS if (self.path / f).is_dir()), None)
        self._files: dict[tuple[Path, str], dict[int, Path]] = {}
        # read quietly for its cameras first: sizes the file lacks (EasyMocap's write_intri writes
        # none) come from the images, and a size taken from them is not warned of as guessed
        quiet = load_calibration(source, units, fmt=fmt, warn=lambda line: None)
        sizes = self._first_image_sizes(quiet) if any(c.size_guessed for c in quiet) else None
        self.user_studio: Studio = load_calibration(source, units, fmt=fmt, image_sizes=sizes, images=str(self.path))
        # fitting runs in the z-up fit frame (common.world); results go back to the user's
        self.world: WorldFrame = resolve_world(self.user_studio, up)
        if (warning := below_floor_warning(self.user_studio, self.world)) is not None:
            print_warning(f"{self.path}: {warning}")
        self.studio: Studio = self.world.studio_to_fit(self.user_studio)
        self.left_out: tuple[str, ...] = ()  # cameras left out (``without_cameras``)
        self.foreground_left_out: np.ndarray | None = None  # (K, H, W) bool pixels cleared (``without_foreground``)
        self.clean_masks = clean_masks
        self._cleaned: OrderedDict = OrderedDict()  # frame -> (packed masks, width, pixels removed per camera)
        self._cleaned_bytes = 0
        self._cleaned_lock = threading.Lock()
        self._props: tuple[StaticProps | None] | None = None  # (props,) once looked for
        self._checked: dict = {}  # (frames, masks, images) -> the cameras check_files passed them for
        meta_path = self.path / "sequence.json"
        self.meta = read_sequence_meta(meta_path) if meta_path.exists() else {}
        self.fps = self.meta.get("fps", DEFAULT_FPS)
        self.frames = self.meta["frames"] if "frames" in self.meta else self._frames_on_disk()
        if not self.frames:
            raise InputFileError(self.path, "no frames (no silhouettes/, mask/ or images/ and no sequence.json)")

    def _first_image_sizes(self, studio: Studio) -> dict[str, tuple[int, int]]:
        """Camera -> (width, height) of its first mask (else colour image), for ``studio``'s
        cameras whose calibration gave no size; cameras without files are left out."""
        sizes = {}
        for cam in studio:
            files = self.mask_files(cam.name) or self.image_files(cam.name)
            if cam.size_guessed and files:
                sizes[cam.name] = image_size(next(iter(files.values())))
        return sizes

    def _frames_on_disk(self) -> list[int]:
        """Every frame any camera has a file for: a frame one camera lacks is then named as
        missing there (``check_files``), never dropped from the others without a word."""
        return sorted(set().union(*(self.mask_files(name) or self.image_files(name) for name in self.studio.names)))

    @property
    def has_silhouettes(self) -> bool:
        return self.mask_folder is not None

    @property
    def padded_shape(self) -> tuple[int, int]:
        """(Hmax, Wmax): the height and width per-frame stacks are padded to."""
        return self.studio.padded_shape

    def _camera_files(self, folder: Path, camera: str) -> dict[int, Path]:
        key = (folder, camera)
        if key not in self._files:
            self._files[key] = frame_files(folder / camera)
        return self._files[key]

    def mask_files(self, camera: str) -> dict[int, Path]:
        """Frame number -> silhouette file of one camera (empty when there are none)."""
        return self._camera_files(self.mask_folder, camera) if self.mask_folder is not None else {}

    def image_files(self, camera: str) -> dict[int, Path]:
        """Frame number -> colour image file of one camera (empty when there are none)."""
        return self._camera_files(self.path / IMAGE_FOLDER, camera)

    def _path(self, folder: Path | None, camera: str, frame: int) -> Path:
        if folder is None:
            folders = "/, ".join(MASK_FOLDERS)
            raise InputFileError(self.path / MASK_FOLDERS[0],
                                 f"missing: no silhouettes ({folders}/ folders); make them with mocap segment")
        files = self._camera_files(folder, camera)
        if frame not in files:
            if not (folder / camera).is_dir():  # an empty silhouettes/ says more than its first file
                held = sorted(p.name for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []
                raise InputFileError(folder / camera, f"missing: no folder for camera {camera} "
                                     + (f"(holds {', '.join(held)})" if held else f"({folder.name}/ holds no camera folder)"))
            raise InputFileError(expected_path(folder / camera, files, frame),
                                 f"missing: frame {frame} of camera {camera}")
        return files[frame]

    def silhouette_path(self, camera: str, frame: int) -> Path:
        """Where ``mocap segment`` writes a silhouette: silhouettes/<camera>/<frame:06d>.png."""
        return self.path / MASK_FOLDERS[0] / camera / FRAME_NAME.format(frame=frame)

    def mask(self, camera, frame: int) -> np.ndarray:
        """(h, w) bool silhouette of one camera (a ``Camera``) in one frame, checked against its size."""
        path = self._path(self.mask_folder, camera.name, frame)
        mask = read_mask(path, self.mask_threshold)
        check_size(mask.shape, path, camera)
        return mask

    def image(self, camera, frame: int) -> np.ndarray:
        """(h, w, 3) uint8 colour image of one camera (a ``Camera``) in one frame."""
        path = self._path(self.path / IMAGE_FOLDER, camera.name, frame)
        image = read_image(path, "RGB")
        check_size(image.shape, path, camera)
        return image

    def silhouettes(self, frame: int) -> np.ndarray:
        """(K, Hmax, Wmax) bool masks of one frame, cameras in calibration order.

        Camera k's mask is in ``[k, :h_k, :w_k]``; the padding is False.
        """
        masks = self.cleaned(frame)[0] if self.clean_masks else self.raw_silhouettes(frame)
        return masks if self.foreground_left_out is None else masks & ~self.foreground_left_out

    def raw_silhouettes(self, frame: int) -> np.ndarray:
        """(K, Hmax, Wmax) bool masks of one frame as the files hold them (``silhouettes`` without
        the multi-view cleaning)."""
        return pad_stack([self.mask(cam, frame) for cam in self.studio])

    def cleaned(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(masks (K, Hmax, Wmax) bool, (K,) pixels removed): one frame's masks without the blobs
        the other cameras do not support and without the take's static props
        (``common.consistency.supported_masks``); the most recent frames' are kept, packed, up
        to CLEANED_BYTES_KEPT."""
        with self._cleaned_lock:  # a fit's threads may ask for a frame at once
            if frame not in self._cleaned:
                raw = self.raw_silhouettes(frame)
                masks, removed = supported_masks(self.studio, raw, silhouette_centre(self.studio, raw),
                                                 self._static_props())
                self._cleaned[frame] = (np.packbits(masks, axis=-1), masks.shape[-1], removed)
                self._cleaned_bytes += self._cleaned[frame][0].nbytes
                while self._cleaned_bytes > CLEANED_BYTES_KEPT and len(self._cleaned) > 1:
                    self._cleaned_bytes -= self._cleaned.popitem(last=False)[1][0].nbytes
            self._cleaned.move_to_end(frame)
            packed, width, removed = self._cleaned[frame]
        return np.unpackbits(packed, axis=-1, count=width).astype(bool), removed

    @property
    def static_props(self) -> StaticProps | None:
        """The take's static props (``common.consistency.static_props``), None when it has none."""
        with self._cleaned_lock:
            return self._static_props()

    def _static_props(self) -> StaticProps | None:
        """``static_props`` with the lock held; looked for once, in PROP_SAMPLES frames across the take."""
        if self._props is None:
            picks = np.unique(np.linspace(0, len(self.frames) - 1, PROP_SAMPLES).round().astype(int))
            samples = [self.raw_silhouettes(self.frames[i]) for i in picks]
            self._props = (static_props(self.studio, samples, silhouette_centre(self.studio, samples[0])),)
        return self._props[0]

    def images(self, frame: int) -> np.ndarray:
        """(K, Hmax, Wmax, 3) uint8 colour images of one frame; camera k's in ``[k, :h_k, :w_k]``, zero padded."""
        return pad_stack([self.image(cam, frame) for cam in self.studio], dtype=np.uint8)

    def check_files(self, frames, masks: bool = True, images: bool = False) -> None:
        """Raise InputFileError for the first missing or unusable silhouette (with ``masks``) or
        colour image (with ``images``) of ``frames``: all files are looked for first, then each
        is checked as ``silhouettes`` would read it (read in full: size, binary mask) or, for
        colour images, from its header (size, readable). A check this sequence passed already
        (the same frames and kinds, for these cameras or more: ``mocap fit`` checks before its
        size search, and the fit again after leaving cameras out) is not read again.
        """
        frames = list(frames)
        done = (tuple(frames), masks, images)
        if set(self.studio.names) <= self._checked.get(done, set()):
            return
        folders = ([self.mask_folder] if masks else []) + ([self.path / IMAGE_FOLDER] if images else [])
        for folder in folders:
            for frame in frames:
                for cam in self.studio:
                    self._path(folder, cam.name, frame)
        for frame in frames:
            for cam in self.studio:
                if masks:
                    self.mask(cam, frame)
                if images:
                    path = self._path(self.path / IMAGE_FOLDER, cam.name, frame)
                    width, height = image_size(path)
                    check_size((height, width), path, cam)
        self._checked[done] = set(self.studio.names)

    def constant_cameras(self, frames) -> dict[str, str]:
        """Camera name -> "on", "off" or "on or off" for each camera whose mask is all on or all
        off in every one of ``frames`` (a camera that sees nothing of the actor, or whose masks
        failed). Cheap: a camera's scan stops at its first mask with both silhouette and background."""
        frames = list(frames)
        found = {}
        for cam in self.studio:
            states = set()
            for frame in frames:
                mask = self.mask(cam, frame)
                on = bool(mask.any())
                if on and not mask.all():
                    break
                states.add("on" if on else "off")
            else:
                if frames:
                    found[cam.name] = " or ".join(sorted(states, reverse=True))
        return found

    def without_cameras(self, names) -> "Sequence":
        """The same sequence with the cameras ``names`` left out (the world frame is still the
        one all cameras gave); before ``without_foreground``, whose pixels are the cameras'."""
        names = set(names)
        out = copy.copy(self)
        out.user_studio = Studio(tuple(c for c in self.user_studio if c.name not in names), self.user_studio.source)
        out.studio = Studio(tuple(c for c in self.studio if c.name not in names), self.studio.source)
        out.left_out = tuple(sorted(set(self.left_out) | (names & set(self.user_studio.names))))
        out._cleaned, out._cleaned_bytes, out._cleaned_lock, out._props = OrderedDict(), 0, threading.Lock(), None
        return out

    def without_foreground(self, pixels: np.ndarray) -> "Sequence":
        """The same sequence with the pixels ``pixels`` (K, Hmax, Wmax) bool, over the images as
        recorded, cleared in every frame's silhouettes (foreground no fitted pose explains:
        ``common.consistency.unexplained_foreground``)."""
        out = copy.copy(self)
        out.foreground_left_out = np.asarray(pixels, dtype=bool)
        return out

    def truth(self) -> dict[int, TruthFrame] | None:
        """Ground truth per frame number, or None when the sequence has none."""
        path = self.path / "truth.jsonl"
        if not path.exists():
            return None
        return {t.frame: t for t in read_truth(path)}


def read_sequence_meta(path: Path) -> dict:
    """sequence.json, its fields checked: ``frames`` a non-empty list of distinct whole numbers
    >= 0 (the numbers in frame file names), ``fps`` a finite number > 0, ``cameras`` a list of
    names. Other fields (``segmentation``, ``source``, ...) are records for the user, kept as
    they are."""
    checks = FieldChecks(path)
    meta = checks.object(checks.parse_json(checks.read()), "<root>")
    if "fps" in meta:
        meta["fps"] = checks.number(meta["fps"], "fps", minimum=0.0, exclusive_minimum=True)
    if "frames" in meta:
        listed = checks.items(meta["frames"], "frames")
        if not listed:
            raise checks.error("frames", "an empty list; list the frame numbers, or leave frames out to fit "
                                         "every frame on disk")
        frames = [checks.whole(f, f"frames[{i}]", minimum=0) for i, f in enumerate(listed)]
        if len(set(frames)) != len(frames):
            twice = next(f for f in frames if frames.count(f) > 1)
            raise checks.error("frames", f"frame {twice} listed twice")
        meta["frames"] = frames
    if "cameras" in meta:
        cameras = checks.items(meta["cameras"], "cameras")
        meta["cameras"] = [checks.text(c, f"cameras[{i}]") for i, c in enumerate(cameras)]
    return meta


def read_truth(path: Path) -> list[TruthFrame]:
    """truth.jsonl: one JSON object a line, ``{"frame": N, "params": [35 numbers], "joints":
    {name: [x, y, z], ...}}`` with every joint of ``JOINT_NAMES`` (metres); blank lines skipped."""
    whole_file = FieldChecks(path)
    out = []
    for lineno, line in enumerate(whole_file.decode(whole_file.read()).split("\n"), 1):
        if not line.strip():
            continue
        checks = FieldChecks(path, line=lineno)
        doc = checks.object(checks.parse_json(line.encode()), "<record>")
        for key in ("frame", "params", "joints"):
            if key not in doc:
                raise checks.error(key, "missing")
        joints = checks.object(doc["joints"], "joints")
        absent = [n for n in JOINT_NAMES if n not in joints]
        if absent:
            raise checks.error("joints", f"no {', '.join(absent)}")
        out.append(TruthFrame(
            checks.whole(doc["frame"], "frame", minimum=0),
            np.array(checks.numbers(doc["params"], "params", len(PARAM_NAMES))),
            {name: np.array(checks.numbers(v, f"joints.{name}", 3)) for name, v in joints.items()}))
    return out


def write_sequence_meta(path, frames, fps: float, cameras: list[str], **extra) -> None:
    doc = {"frames": [int(f) for f in frames], "fps": float(fps), "cameras": list(cameras), **extra}
    Path(path, "sequence.json").write_text(json.dumps(doc, indent=1))


def load_sequence(path, units: str | None = None, mask_threshold: int | None = None, up: str = "auto",
                  clean_masks: bool = True, calibration=None) -> Sequence:
    return Sequence(path, units, mask_threshold, up, clean_masks, calibration)
