"""The world's up axis: calibrations as labs have them, fitted in our z-up frame.

A checkerboard lying on the floor makes a world whose z axis points down (the board's normal
into the floor); OpenSim and Pose2Sim worlds have y up. The body model stands on z = 0 with z
up, so a sequence is fitted in the *fit frame*: the user's world turned so that its up axis is
+z (a proper rotation about the origin, so the floor stays at height 0 and lengths and units are
unchanged). Joint positions are written back in the user's frame.

``detect_up`` reads the up axis from the cameras: they stand above the floor and their images'
up direction (-y of the camera) points up in the world, roughly. A camera mounted upside down or
looking straight down gives no vote on the image direction but its height still counts.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from common.camera import Studio
from common.errors import UserError

UP_CHOICES = ("auto", "+z", "-z", "+y", "-y", "+x", "-x")
# user -> fit frame rotations W (x_fit = W @ x_user) taking each axis to +z, det +1
_TO_Z_UP = {
    "+z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),                                   # half a turn about x
    "+y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "-y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "+x": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
    "-x": np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
}
AXIS_VECTORS = {name: W[2] for name, W in _TO_Z_UP.items()}  # the user-frame direction that becomes +z
MIN_CAMERA_HEIGHT = 0.05  # metres: a camera this far below the floor for the chosen axis is warned about


@dataclass(frozen=True)
class WorldFrame:
    """How the user's world relates to the fit frame.

    up: the user's up axis ("+z", "-z", "+y", ...); rotation: (3, 3) W with x_fit = W @ x_user.
    """

    up: str
    rotation: np.ndarray

    @property
    def is_identity(self) -> bool:
        return self.up == "+z"

    def studio_to_fit(self, studio: Studio) -> Studio:
        """Cameras re-expressed in the fit frame: x_cam = R x_user + t = (R W^T) x_fit + t."""
        if self.is_identity:
            return studio
        return Studio(tuple(replace(c, R=c.R @ self.rotation.T) for c in studio), studio.source)

    def studio_to_user(self, studio: Studio) -> Studio:
        """Fit-frame cameras re-expressed in the user's world, the inverse of ``studio_to_fit``:
        x_cam = R x_fit + t = (R W) x_user + t."""
        if self.is_identity:
            return studio
        return Studio(tuple(replace(c, R=c.R @ self.rotation) for c in studio), studio.source)

    def points_to_user(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) fit-frame points -> the user's frame."""
        return np.asarray(points, dtype=np.float64) @ self.rotation

    def points_to_fit(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) user-frame points -> the fit frame."""
        return np.asarray(points, dtype=np.float64) @ self.rotation.T


def world_frame(up: str) -> WorldFrame:
    """The WorldFrame of an explicit up axis ("+z", "-z", "+y", "-y", "+x", "-x")."""
    if up not in _TO_Z_UP:
        raise UserError(f"--up: expected one of {', '.join(UP_CHOICES)}, got {up!r}")
    return WorldFrame(up, _TO_Z_UP[up].copy())


def up_scores(studio: Studio) -> dict[str, float]:
    """Per candidate up axis, how well the cameras agree with it (higher is better).

    Each camera adds the cosine between its image-up direction (-R[1], world frame) and the
    axis, plus 1 if it stands above the floor (its centre's height along the axis > 0) and -1
    if below. Heights alone tell +z from -z; the image direction tells z from y.
    """
    scores = {}
    for name, axis in AXIS_VECTORS.items():
        s = 0.0
        for c in studio:
            s += float(-c.R[1] @ axis)
            s += float(np.sign(c.center @ axis))
        scores[name] = s
    return scores


def detect_up(studio: Studio) -> str:
    """The user's up axis as the cameras show it (see ``up_scores``)."""
    scores = up_scores(studio)
    return max(scores, key=lambda k: (scores[k], k == "+z"))  # ties keep our own convention


def resolve_world(studio: Studio, up: str = "auto") -> WorldFrame:
    """The WorldFrame for ``up`` ("auto": ``detect_up``) of ``studio`` (user frame)."""
    return world_frame(detect_up(studio) if up == "auto" else up)


def cameras_below_floor(studio: Studio, world: WorldFrame) -> list[str]:
    """Names of cameras whose centre is below the floor (height < -MIN_CAMERA_HEIGHT) for ``world``."""
    axis = AXIS_VECTORS[world.up]
    return [c.name for c in studio if float(c.center @ axis) < -MIN_CAMERA_HEIGHT]


def below_floor_warning(studio: Studio, world: WorldFrame) -> str | None:
    """The warning for cameras that ``world``'s up axis puts below the floor (a z-down board
    calibration fitted with --up +z comes out upside down), or None."""
    below = cameras_below_floor(studio, world)
    if not below:
        return None
    return (f"with up {world.up} cameras {', '.join(below)} stand below the floor ({world.up[1]} = 0); "
            f"is the up axis right? (auto finds {detect_up(studio)})")
