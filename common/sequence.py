"""Sequence folders: calibration, per-camera silhouettes or images, optional ground truth.

Layout (see docs/CONTRIBUTING.md)::

    SEQUENCE/calibration.json
    SEQUENCE/sequence.json                        {"frames": [...], "fps": 30.0, "cameras": [...]}
    SEQUENCE/silhouettes/<camera>/<frame:06d>.png
    SEQUENCE/images/<camera>/<frame:06d>.png
    SEQUENCE/background/<camera>/<n:06d>.png
    SEQUENCE/truth.jsonl
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from common.calibration import load_calibration
from common.camera import Studio
from common.errors import InputFileError

FRAME_NAME = "{frame:06d}.png"
DEFAULT_FPS = 30.0  # frames per second when sequence.json does not say


@dataclass(frozen=True)
class TruthFrame:
    frame: int
    params: np.ndarray  # (35,)
    joints: dict  # name -> (3,) metres


def read_png(path: Path, mode: str) -> np.ndarray:
    """Read one PNG as an array ('L' -> (H, W) uint8, 'RGB' -> (H, W, 3) uint8)."""
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert(mode))
    except FileNotFoundError:
        raise InputFileError(path, "missing") from None
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise InputFileError(path, f"not a readable image ({exc})") from None


def write_mask_png(path: Path, mask: np.ndarray) -> None:
    """(H, W) bool -> 1-bit PNG (compact, lossless)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(mask, dtype=bool)).save(path, optimize=False)


class Sequence:
    """A sequence folder opened for reading."""

    def __init__(self, path, units: str | None = None):
        self.path = Path(path)
        if not self.path.is_dir():
            raise InputFileError(self.path, "not a sequence folder (does not exist)")
        self.studio: Studio = load_calibration(self.path / "calibration.json", units)
        meta_path = self.path / "sequence.json"
        meta = {}
        if meta_path.exists():
            try:
                meta = json.loads(meta_path.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise InputFileError(meta_path, f"not valid JSON ({exc})") from None
        self.meta = meta
        self.fps = float(meta.get("fps", DEFAULT_FPS))
        if "frames" in meta:
            self.frames = [int(f) for f in meta["frames"]]
        else:
            self.frames = self._frames_on_disk()
        if not self.frames:
            raise InputFileError(self.path, "no frames (no silhouettes/ or images/ and no sequence.json)")

    def _frames_on_disk(self) -> list[int]:
        for sub in ("silhouettes", "images"):
            cam_dir = self.path / sub / self.studio.names[0]
            if cam_dir.is_dir():
                return sorted(int(p.stem) for p in cam_dir.glob("*.png") if p.stem.isdigit())
        return []

    @property
    def has_silhouettes(self) -> bool:
        return (self.path / "silhouettes").is_dir()

    def silhouette_path(self, camera: str, frame: int) -> Path:
        return self.path / "silhouettes" / camera / FRAME_NAME.format(frame=frame)

    def silhouettes(self, frame: int) -> np.ndarray:
        """(K, H, W) bool masks of one frame, cameras in calibration order."""
        masks = []
        for cam in self.studio:
            path = self.silhouette_path(cam.name, frame)
            img = read_png(path, "L")
            if img.shape != (cam.height, cam.width):
                raise InputFileError(path, f"size {img.shape[1]}x{img.shape[0]} does not match the "
                                           f"calibration of {cam.name} ({cam.width}x{cam.height})")
            masks.append(img > 127)
        return np.stack(masks)

    def images(self, frame: int) -> np.ndarray:
        """(K, H, W, 3) uint8 colour images of one frame."""
        out = []
        for cam in self.studio:
            path = self.path / "images" / cam.name / FRAME_NAME.format(frame=frame)
            img = read_png(path, "RGB")
            if img.shape[:2] != (cam.height, cam.width):
                raise InputFileError(path, f"size {img.shape[1]}x{img.shape[0]} does not match the "
                                           f"calibration of {cam.name} ({cam.width}x{cam.height})")
            out.append(img)
        return np.stack(out)

    def truth(self) -> dict[int, TruthFrame] | None:
        """Ground truth per frame number, or None when the sequence has none."""
        path = self.path / "truth.jsonl"
        if not path.exists():
            return None
        return {t.frame: t for t in read_truth(path)}


def read_truth(path: Path) -> list[TruthFrame]:
    out = []
    with open(path) as fh:
        for lineno, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                doc = json.loads(line)
                out.append(TruthFrame(int(doc["frame"]), np.asarray(doc["params"], dtype=np.float64),
                                      {k: np.asarray(v, dtype=np.float64) for k, v in doc["joints"].items()}))
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
                raise InputFileError(path, f"line {lineno}: not a truth record ({exc})") from None
    return out


def write_sequence_meta(path, frames, fps: float, cameras: list[str], **extra) -> None:
    doc = {"frames": [int(f) for f in frames], "fps": float(fps), "cameras": list(cameras), **extra}
    Path(path, "sequence.json").write_text(json.dumps(doc, indent=1))


def load_sequence(path, units: str | None = None) -> Sequence:
    return Sequence(path, units)
