"""Pinhole cameras with lens distortion, and studios (rigs) of K cameras.

World units are metres, z up. A camera maps a world point X to camera coordinates
``Xc = R @ X + t`` and then to pixels with the intrinsic matrix ``K`` after OpenCV's
distortion model (k1, k2, p1, p2, k3). Pixel (0, 0) is the centre of the top-left pixel.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from common.errors import UserError
from common.packing import padded_shape

ORTHONORMAL_TOLERANCE = 1e-6  # max |R^T R - I| entry accepted for a rotation
DIST_COEFFS = 5  # k1 k2 p1 p2 k3


class CalibrationError(UserError, ValueError):
    """A calibration that cannot be used; the message names the file and the field (none where
    the whole file is at fault: missing, unreadable, not the format)."""

    def __init__(self, source: str, field_name: str, problem: str):
        self.source = source
        self.field_name = field_name
        self.problem = problem
        super().__init__(f"{source}: {field_name}: {problem}" if field_name else f"{source}: {problem}")


@dataclass(frozen=True)
class Camera:
    """One calibrated pinhole camera.

    K: (3, 3) intrinsics in pixels; dist: (5,) k1 k2 p1 p2 k3; R: (3, 3) world-to-camera
    rotation; t: (3,) world-to-camera translation in metres; width, height in pixels.
    size_guessed: the calibration file gave no image size and width, height are a guess (twice
    the principal point); ``common.calibration.with_image_sizes`` replaces it with the images'.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    size_guessed: bool = field(default=False, compare=False)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, metres."""
        return -self.R.T @ self.t

    # Cached: a fit asks for these thousands of times per frame, and a camera does not change
    # (its arrays are never written after make_camera).
    @cached_property
    def projection_matrix(self) -> np.ndarray:
        """(3, 4) P = K [R | t] (ignores distortion); read-only."""
        P = self.K @ np.hstack([self.R, self.t[:, None]])
        P.setflags(write=False)
        return P

    @cached_property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 3) camera-frame points."""
        return points @ self.R.T + self.t

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 2) pixel coordinates, with distortion."""
        return self._pixels(self.to_camera(np.asarray(points, dtype=np.float64)))

    def project_with_depth(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) world points -> ((..., 2) pixel coordinates, with distortion, (...,) depth
        along the optical axis, metres): ``project`` and ``depth`` from one transform."""
        xc = self.to_camera(np.asarray(points, dtype=np.float64))
        return self._pixels(xc), xc[..., 2]

    def _pixels(self, xc: np.ndarray) -> np.ndarray:
        """(..., 3) camera-frame points -> (..., 2) pixel coordinates, with distortion."""
        z = xc[..., 2]
        x = xc[..., 0] / z
        y = xc[..., 1] / z
        if self.has_distortion:
            x, y = distort_normalized(x, y, self.dist)
        uv = np.empty(np.shape(x) + (2,))
        uv[..., 0] = self.K[0, 0] * x + self.K[0, 1] * y + self.K[0, 2]
        uv[..., 1] = self.K[1, 1] * y + self.K[1, 2]
        return uv

    def depth(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (...,) depth along the optical axis, metres."""
        return self.to_camera(np.asarray(points, dtype=np.float64))[..., 2]

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """(..., 2) pixel coordinates (with distortion) -> (..., 3) unit world directions of the
        rays through them, from ``center``."""
        uv = np.asarray(uv, dtype=np.float64)
        K = self.K
        y = (uv[..., 1] - K[1, 2]) / K[1, 1]
        x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        if self.has_distortion:
            x, y = undistort_normalized(x, y, self.dist)
        d = np.stack([x, y, np.ones_like(x)], axis=-1) @ self.R  # R^T d for row vectors
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def scaled(self, factor: float) -> "Camera":
        """The same camera at ``factor`` times the resolution (0.5 = half resolution).

        Pixel centres stay consistent: u' = (u + 0.5) * factor - 0.5.
        """
        S = np.array([[factor, 0.0, 0.5 * factor - 0.5], [0.0, factor, 0.5 * factor - 0.5], [0, 0, 1]])
        return Camera(self.name, S @ self.K, self.dist.copy(), self.R.copy(), self.t.copy(),
                      int(round(self.width * factor)), int(round(self.height * factor)), self.size_guessed)


def distort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray):
    """OpenCV radial-tangential distortion of normalized image coordinates."""
    return distortion(x, y, *dist)


def distortion(x, y, k1, k2, p1, p2, k3):
    """``distort_normalized`` with the coefficients apart: plain arithmetic on arrays or
    scalars, so that compiled kernels use it too (``numba.njit(distortion)``, the same bits)."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort_normalized(x: np.ndarray, y: np.ndarray, dist: np.ndarray, iterations: int = 20):
    """Normalised distorted coordinates -> undistorted (fixed-point inversion of
    ``distort_normalized``)."""
    xu, yu = np.array(x, dtype=np.float64), np.array(y, dtype=np.float64)
    for _ in range(iterations):
        xd, yd = distort_normalized(xu, yu, dist)
        xu = xu - (xd - x)
        yu = yu - (yd - y)
    return xu, yu


def make_camera(name: str, K, dist, R, t, width, height, source: str = "<memory>") -> Camera:
    """Validate raw calibration values and build a Camera.

    Raises CalibrationError naming ``source`` and the field at fault.
    """
    field_prefix = f"{name}."
    K = _matrix(K, (3, 3), source, field_prefix + "K")
    R = _matrix(R, (3, 3), source, field_prefix + "R")
    t = _matrix(t, None, source, field_prefix + "t").reshape(-1)
    if t.shape != (3,):
        raise CalibrationError(source, field_prefix + "t", f"expected 3 values, got {t.size}")
    dist = _matrix(dist if dist is not None else np.zeros(DIST_COEFFS), None, source,
                   field_prefix + "dist").reshape(-1)
    if dist.size > DIST_COEFFS:
        if np.any(dist[DIST_COEFFS:] != 0.0):
            raise CalibrationError(source, field_prefix + "dist",
                                   f"only {DIST_COEFFS} coefficients (k1 k2 p1 p2 k3) are supported, got {dist.size}")
        dist = dist[:DIST_COEFFS]
    dist = np.concatenate([dist, np.zeros(DIST_COEFFS - dist.size)])
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > ORTHONORMAL_TOLERANCE or np.linalg.det(R) < 0:
        raise CalibrationError(source, field_prefix + "R",
                               f"not a rotation (|R^T R - I| = {err:.2e}, det = {np.linalg.det(R):.3f})")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-9 or np.any(K[1:, 0] != 0) or K[2, 1] != 0:
        raise CalibrationError(source, field_prefix + "K",
                               "expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    try:
        width, height = int(width), int(height)
    except (TypeError, ValueError):
        raise CalibrationError(source, field_prefix + "size", f"not integers: {width!r} x {height!r}") from None
    if width <= 0 or height <= 0:
        raise CalibrationError(source, field_prefix + "size", f"must be positive, got {width} x {height}")
    return Camera(str(name), K, dist, R, t, width, height)


def _matrix(value, shape, source, field_name) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(source, field_name, f"not numeric: {value!r}") from None
    if shape is not None and arr.shape != shape:
        if arr.size == int(np.prod(shape)):
            arr = arr.reshape(shape)
        else:
            raise CalibrationError(source, field_name, f"expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(source, field_name, "contains NaN or infinity")
    return arr


@dataclass(frozen=True)
class Studio:
    """K calibrated cameras, in a fixed order (the bit order of packed silhouettes)."""

    cameras: tuple[Camera, ...]
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self):
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise CalibrationError(self.source, "cameras", f"duplicate camera names: {names}")
        if not self.cameras:
            raise CalibrationError(self.source, "cameras", "no cameras")

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self):
        return iter(self.cameras)

    def __getitem__(self, index: int) -> Camera:
        return self.cameras[index]

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @cached_property
    def projection_matrices(self) -> np.ndarray:
        """(K, 3, 4) the cameras' P (``Camera.projection_matrix``), never written (left writable:
        the compiled kernels are compiled for writable arrays, a read-only one would be another
        signature to compile)."""
        return np.stack([c.projection_matrix for c in self.cameras])

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """(K, 2) (width, height) of each camera's image, pixels."""
        return [(c.width, c.height) for c in self.cameras]

    @property
    def padded_shape(self) -> tuple[int, int]:
        """(H, W) of the cameras' padded per-frame stacks (``packing.pad_stack``): the largest
        image height and the largest width."""
        return padded_shape(self.sizes)

    def camera(self, name: str) -> Camera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)

    def scaled(self, factor: float) -> "Studio":
        return Studio(tuple(c.scaled(factor) for c in self.cameras), self.source)

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (K, N, 2) pixels."""
        return np.stack([c.project(points) for c in self.cameras])


def look_at(name: str, eye, target, width: int, height: int, fov_y_deg: float = 50.0,
            up=(0.0, 0.0, 1.0)) -> Camera:
    """A distortion-free camera at ``eye`` looking at ``target`` (world z up)."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    up = np.asarray(up, dtype=np.float64)
    if abs(forward @ up) > 0.999:  # looking straight down: use world y as the image "up"
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # camera x right, y down, z forward (OpenCV)
    t = -R @ eye
    f = 0.5 * height / np.tan(np.radians(fov_y_deg) / 2.0)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return Camera(name, K, np.zeros(DIST_COEFFS), R, t, int(width), int(height))


def circle_studio(count: int = 8, width: int = 320, height: int = 240, radius: float = 3.0,
                  height_m: float = 1.5, target=(0.0, 0.0, 0.9), overhead: bool = True,
                  fov_y_deg: float = 55.0) -> Studio:
    """The virtual studio: cameras on a circle looking at the actor, plus one overhead.

    With ``overhead`` and count >= 5, the last camera looks straight down from 3.5 m.
    """
    ring = count - 1 if (overhead and count >= 5) else count
    cams = []
    for i in range(ring):
        a = 2.0 * np.pi * i / ring
        eye = (radius * np.cos(a), radius * np.sin(a), height_m)
        cams.append(look_at(f"cam{i + 1}", eye, target, width, height, fov_y_deg))
    if ring < count:
        cams.append(look_at(f"cam{count}", (0.0, 0.0, 3.5), (0.0, 0.0, 0.0), width, height, 70.0))
    return Studio(tuple(cams))
