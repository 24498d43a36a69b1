"""Whole-body postures beyond standing, from joint angles: seated, crouching, kneeling, lying.

Two users: the first-frame search, whose starts otherwise assume an upright or head-down body
(a seated person fitted from a standing start ends standing, the legs stretched down the
chair's front), and the virtual studio, which makes truth for such poses (none of the CMU
clips sits, crouches or lies).

A posture is a set of joint angles (radians; the rest of the 35 parameters as in the rest
pose); ``posture_params`` places it at a floor position and heading, with the pelvis height
chosen so that the body's lowest surface point touches the floor (z = 0).
"""
from __future__ import annotations

import numpy as np

from common.body import P, BodyModel, clip_to_limits, forward_kinematics, rest_params, rigid_vertices

# Joint angles per posture (radians). Hip x < 0 swings the thigh forward, knee > 0 bends it;
# root tilt x > 0 leans the trunk forward.
POSTURES: dict[str, dict[str, float]] = {
    "seated": {"l_hip_x": -1.5, "r_hip_x": -1.5, "l_knee": 1.5, "r_knee": 1.5,
               "l_shoulder_x": -0.5, "r_shoulder_x": -0.5, "l_elbow": 1.2, "r_elbow": 1.2},
    "crouching": {"root_tilt_x": 0.6, "l_hip_x": -2.2, "r_hip_x": -2.2, "l_knee": 2.3, "r_knee": 2.3,
                  "l_ankle_flex": 0.5, "r_ankle_flex": 0.5,
                  "l_shoulder_x": -0.8, "r_shoulder_x": -0.8, "l_elbow": 0.8, "r_elbow": 0.8},
    "kneeling": {"l_hip_x": -0.1, "r_hip_x": -0.1, "l_knee": 1.6, "r_knee": 1.6,
                 "l_ankle_flex": -0.8, "r_ankle_flex": -0.8},
    "kneeling_one": {"l_hip_x": -1.5, "l_knee": 1.5, "r_hip_x": -0.1, "r_knee": 1.6, "r_ankle_flex": -0.8},
    "lying_back": {"root_tilt_x": -1.5707963267948966},
    "lying_front": {"root_tilt_x": 1.5707963267948966},
    "lying_side": {"root_tilt_y": 1.5707963267948966, "l_hip_x": -0.4, "r_hip_x": -0.2, "l_knee": 0.6,
                   "r_knee": 0.4},
}
# The postures the first-frame search starts from, beside its standing and head-down starts.
SEARCH_POSTURES = ("seated", "crouching", "kneeling", "lying_back", "lying_front", "lying_side")


def posture_params(model: BodyModel, posture: str | dict, x: float = 0.0, y: float = 0.0,
                   heading: float = 0.0, floor: float = 0.0) -> np.ndarray:
    """(35,) ``posture`` (a name in POSTURES or a dict of joint angles) with its pelvis above
    (x, y), turned by ``heading`` about the vertical, the lowest surface point at ``floor``."""
    angles = POSTURES[posture] if isinstance(posture, str) else posture
    params = rest_params(model, position=(x, y, 0.0), heading=heading)
    for name, value in angles.items():
        params[P[name]] = value
    params = clip_to_limits(params)
    lowest = rigid_vertices(model, forward_kinematics(model, params))[:, 2].min()
    params[P["root_z"]] += floor - lowest
    return params


def varied_posture(model: BodyModel, posture: str, rng: np.random.Generator, spread: float = 0.15,
                   x: float = 0.0, y: float = 0.0, heading: float = 0.0) -> np.ndarray:
    """(35,) ``posture`` with each of its joint angles moved by a normal draw of ``spread``
    radians, on the floor at (x, y, heading): seeded variation for the virtual studio."""
    angles = {k: v + float(rng.normal(0.0, spread)) for k, v in POSTURES[posture].items()}
    return posture_params(model, angles, x, y, heading)
