"""The articulated body: 16 rigid segments, 17 joints, 35 pose parameters (Theobalt et al. 2003).

World: metres, z up; in the rest pose the actor faces -y with its left side towards +x.

Parameters (index: name), angles in radians:
    0-2   root_x root_y root_z        pelvis joint position
    3     root_heading                rotation about world z (unbounded, unwrapped)
    4-5   root_tilt_x root_tilt_y     tilt as a rotation vector in the heading frame
    6-8   spine_x spine_y spine_z     rotation vector, shared half/half by the abdomen and chest
    9-10  neck_nod neck_turn
    11-13 l_shoulder_x/y/z            rotation vector relative to the rest pose
    14    l_elbow                     flexion, 0 = straight
    15-16 l_wrist_flex l_wrist_dev
    17-22 the same for the right arm
    23-25 l_hip_x/y/z                 rotation vector relative to the rest pose
    26    l_knee                      flexion, 0 = straight
    27-28 l_ankle_flex l_ankle_inv
    29-34 the same for the right leg
Rotation vectors (exponential maps) have no gimbal lock inside |angle| < pi, which keeps
Powell's line searches well conditioned; the root uses heading + tilt so that turning on the
spot (pirouettes) never wraps.

One module of about 640 lines: the kinematic tree, its parameters and limits, forward
kinematics and the mesh/ellipsoid surfaces are the body model every other module takes.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property, lru_cache
from importlib import resources

import numpy as np
from numba import njit

SEGMENT_NAMES = (
    "pelvis", "abdomen", "chest", "head",
    "l_upperarm", "l_forearm", "l_hand", "r_upperarm", "r_forearm", "r_hand",
    "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot",
)
SEGMENT_PARENTS = (-1, 0, 1, 2, 2, 4, 5, 2, 7, 8, 0, 10, 11, 0, 13, 14)
# Joint i < 16 is the origin of segment i; head_top is a point on the head.
JOINT_NAMES = (
    "pelvis", "spine", "chest", "neck",
    "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
    "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle", "head_top",
)
HEAD_TOP_SEGMENT = 3

PARAM_NAMES = (
    "root_x", "root_y", "root_z", "root_heading", "root_tilt_x", "root_tilt_y",
    "spine_x", "spine_y", "spine_z", "neck_nod", "neck_turn",
    "l_shoulder_x", "l_shoulder_y", "l_shoulder_z", "l_elbow", "l_wrist_flex", "l_wrist_dev",
    "r_shoulder_x", "r_shoulder_y", "r_shoulder_z", "r_elbow", "r_wrist_flex", "r_wrist_dev",
    "l_hip_x", "l_hip_y", "l_hip_z", "l_knee", "l_ankle_flex", "l_ankle_inv",
    "r_hip_x", "r_hip_y", "r_hip_z", "r_knee", "r_ankle_flex", "r_ankle_inv",
)
PARAM_COUNT = len(PARAM_NAMES)
P = {name: i for i, name in enumerate(PARAM_NAMES)}

_INF = np.inf
# Joint limits (radians, metres): anatomical ranges, generous enough for dance.
_LIMITS = {
    "root_x": (-_INF, _INF), "root_y": (-_INF, _INF), "root_z": (-_INF, _INF),
    "root_heading": (-_INF, _INF), "root_tilt_x": (-2.9, 2.9), "root_tilt_y": (-2.9, 2.9),
    "spine_x": (-0.7, 1.5), "spine_y": (-0.8, 0.8), "spine_z": (-1.0, 1.0),
    "neck_nod": (-0.9, 1.0), "neck_turn": (-1.4, 1.4),
    "shoulder_x": (-3.0, 3.0), "shoulder_y": (-3.0, 3.0), "shoulder_z": (-3.0, 3.0),
    "elbow": (-0.1, 2.7), "wrist_flex": (-1.3, 1.3), "wrist_dev": (-0.6, 0.7),
    "hip_x": (-2.7, 1.4), "hip_y": (-1.6, 1.6), "hip_z": (-1.3, 1.3),
    "knee": (-0.1, 2.7), "ankle_flex": (-1.0, 1.0), "ankle_inv": (-0.7, 0.7),
}


def _limits_array() -> np.ndarray:
    out = np.empty((PARAM_COUNT, 2))
    for i, name in enumerate(PARAM_NAMES):
        key = name if name in _LIMITS else name[2:]
        out[i] = _LIMITS[key]
    return out


PARAM_LIMITS = _limits_array()  # (35, 2) lower, upper


@dataclass(frozen=True)
class Chain:
    """A kinematic sub-chain: the parameters it owns and the segments they move."""

    name: str
    params: tuple[int, ...]
    segments: tuple[int, ...]  # segments rendered while this chain is optimized


def _seg(*names):
    return tuple(SEGMENT_NAMES.index(n) for n in names)


CHAINS = {
    "torso": Chain("torso", tuple(range(0, 9)), tuple(range(16))),
    "head": Chain("head", (9, 10), _seg("head")),
    "left_arm": Chain("left_arm", tuple(range(11, 17)), _seg("l_upperarm", "l_forearm", "l_hand")),
    "right_arm": Chain("right_arm", tuple(range(17, 23)), _seg("r_upperarm", "r_forearm", "r_hand")),
    "left_leg": Chain("left_leg", tuple(range(23, 29)), _seg("l_thigh", "l_shin", "l_foot")),
    "right_leg": Chain("right_leg", tuple(range(29, 35)), _seg("r_thigh", "r_shin", "r_foot")),
}
LIMB_CHAINS = ("left_arm", "right_arm", "left_leg", "right_leg")
# Within a limb chain: the proximal part (grid search + Powell, 128x128 windows) and the
# extremity (Powell, 64x64 windows), the paper's steps 2 and 3.
LIMB_PARTS = {
    "left_arm": ((11, 12, 13, 14), (15, 16), _seg("l_hand")),
    "right_arm": ((17, 18, 19, 20), (21, 22), _seg("r_hand")),
    "left_leg": ((23, 24, 25, 26), (27, 28), _seg("l_foot")),
    "right_leg": ((29, 30, 31, 32), (33, 34), _seg("r_foot")),
}


@dataclass(frozen=True)
class BodyModel:
    """Rest geometry of one actor. Arrays are read-only views shared by all users.

    joint_rest: (17, 3) rest joint positions; vertices: (V, 3) rest surface; triangles: (T, 3);
    triangle_segment: (T,); vertex_segment: (V,); skin_weights: (V, 16);
    ellipsoid_centres (16, 3), ellipsoid_axes (16, 3, 3) (columns), ellipsoid_radii (16, 3),
    all in segment-local coordinates (rest orientation, origin at the segment's joint).
    hinge_axes: (16, 3, 3) per-segment local axes used by 1- and 2-DOF joints.
    """

    joint_rest: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_segment: np.ndarray
    vertex_segment: np.ndarray
    skin_weights: np.ndarray
    ellipsoid_centres: np.ndarray
    ellipsoid_axes: np.ndarray
    ellipsoid_radii: np.ndarray
    scale: float = 1.0

    @cached_property
    def offsets(self) -> np.ndarray:
        """(16, 3) each segment's origin relative to its parent's, rest pose (read-only)."""
        off = self.joint_rest[:16].copy()
        for s, p in enumerate(SEGMENT_PARENTS):
            if p >= 0:
                off[s] = self.joint_rest[s] - self.joint_rest[p]
        off.setflags(write=False)
        return off

    @cached_property
    def fingerprint(self) -> str:
        """16 hex digits identifying the geometry (scale included): a cluster's server and
        clients must fit the same body, or their limbs would not fit together."""
        digest = hashlib.sha256()
        for a in (self.joint_rest, self.vertices, self.triangles, self.skin_weights, self.ellipsoid_centres,
                  self.ellipsoid_axes, self.ellipsoid_radii):
            digest.update(np.ascontiguousarray(a).tobytes())
        return digest.hexdigest()[:16]

    @property
    def head_top_offset(self) -> np.ndarray:
        return self.joint_rest[16] - self.joint_rest[HEAD_TOP_SEGMENT]

    @cached_property
    def kinematic_tables(self) -> tuple:
        """What forward kinematics needs besides the parameters, built once per model (it runs
        on every evaluation): rest offsets of the hinges (35,), the parameter-to-rotation-vector
        map as each parameter's joint (35,) int (-1: none, the root position and the headings)
        and its axis (35, 3), segment offsets (16, 3), the head top's offset (3,)."""
        key = np.ascontiguousarray(self.joint_rest, dtype=np.float64).tobytes()
        return (_rest_offsets_vector(self), *_parameter_joints(key), self.offsets,
                np.ascontiguousarray(self.head_top_offset))

    def scaled(self, factor: float) -> "BodyModel":
        """The same body uniformly scaled (an actor of another height)."""
        return BodyModel(self.joint_rest * factor, self.vertices * factor, self.triangles,
                         self.triangle_segment, self.vertex_segment, self.skin_weights,
                         self.ellipsoid_centres * factor, self.ellipsoid_axes,
                         self.ellipsoid_radii * factor, self.scale * factor)

    @property
    def height(self) -> float:
        return float(self.vertices[:, 2].max() - self.vertices[:, 2].min())


@lru_cache(maxsize=1)
def load_body_model() -> BodyModel:
    """The default actor (MakeHuman base mesh, about 1.7 m)."""
    with resources.files("common.data").joinpath("body_model.npz").open("rb") as fh:
        data = np.load(fh)
        arrays = {k: data[k] for k in data.files}
    # stored as float16 to stay small: renormalise so every vertex's weights sum to exactly 1
    weights = arrays["skin_weights"].astype(np.float64)
    arrays["skin_weights"] = weights / weights.sum(axis=1, keepdims=True)
    for arr in arrays.values():
        arr.setflags(write=False)
    return BodyModel(**arrays)


# ----------------------------------------------------------------------------- rotations

def rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) matrices (Rodrigues, stable near zero)."""
    rv = np.asarray(rv, dtype=np.float64)
    return _rotvecs_to_matrices(np.ascontiguousarray(rv.reshape(-1, 3))).reshape(rv.shape + (3,))


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 3) rotation vectors with angle in [0, pi]
    (through the quaternion by Shepperd's method, as scipy does)."""
    R = np.asarray(R, dtype=np.float64)
    return _matrices_to_rotvecs(np.ascontiguousarray(R.reshape(-1, 3, 3))).reshape(R.shape[:-2] + (3,))


def rot_z(angle: np.ndarray) -> np.ndarray:
    """(...,) angles -> (..., 3, 3) rotations about the vertical axis."""
    angle = np.asarray(angle, dtype=np.float64)
    return _rotations_z(np.ascontiguousarray(angle.reshape(-1))).reshape(angle.shape + (3, 3))


# ------------------------------------------------------------------------ joint axes

FORWARD = np.array([0.0, -1.0, 0.0])  # the actor's front in the rest pose
LATERAL = np.array([1.0, 0.0, 0.0])   # towards the actor's left


def _unit(v):
    return v / np.linalg.norm(v)


@lru_cache(maxsize=8)
def _joint_frames(joint_rest_bytes: bytes):
    joint_rest = np.frombuffer(joint_rest_bytes).reshape(17, 3)
    J = {n: joint_rest[i] for i, n in enumerate(JOINT_NAMES)}
    out = {}
    for side in ("l", "r"):
        upper = _unit(J[f"{side}_elbow"] - J[f"{side}_shoulder"])
        fore = _unit(J[f"{side}_wrist"] - J[f"{side}_elbow"])
        elbow_axis = _unit(np.cross(upper, FORWARD))  # flexion brings the forearm forward
        rest_elbow = np.arctan2(np.cross(upper, fore) @ elbow_axis, upper @ fore)
        wrist_dev_axis = _unit(np.cross(elbow_axis, fore))
        thigh = _unit(J[f"{side}_knee"] - J[f"{side}_hip"])
        shin = _unit(J[f"{side}_ankle"] - J[f"{side}_knee"])
        knee_axis = _unit(np.cross(thigh, -FORWARD))  # flexion brings the shin backwards
        rest_knee = np.arctan2(np.cross(thigh, shin) @ knee_axis, thigh @ shin)
        out[side] = dict(elbow_axis=elbow_axis, rest_elbow=rest_elbow, wrist_dev_axis=wrist_dev_axis,
                         knee_axis=knee_axis, rest_knee=rest_knee, ankle_inv_axis=FORWARD.copy())
    return out


def joint_frames(model: BodyModel) -> dict:
    """Hinge axes and rest flexion angles of elbows and knees, per side ('l', 'r')."""
    return _joint_frames(np.ascontiguousarray(model.joint_rest, dtype=np.float64).tobytes())


# ------------------------------------------------------------------- forward kinematics

@dataclass(frozen=True)
class Pose:
    """Forward kinematics of a batch of parameter vectors.

    rotations: (B, 16, 3, 3) segment orientations in the world;
    origins: (B, 16, 3) segment origins (joint positions) in the world;
    joints: (B, 17, 3) the 17 joint positions.
    """

    rotations: np.ndarray
    origins: np.ndarray
    joints: np.ndarray


@lru_cache(maxsize=8)
def _axis_table(joint_rest_bytes: bytes) -> np.ndarray:
    """(35, 19, 3) linear map from parameters to the 19 rotation vectors local_rotations uses."""
    f = _joint_frames(joint_rest_bytes)
    M = np.zeros((PARAM_COUNT, 19, 3))
    M[4, 0, 0] = M[5, 0, 1] = 1.0                     # root tilt (heading applied separately)
    for i in range(3):
        M[6 + i, 1, i] = 0.5                          # half the spine rotation at each spine joint
    M[9, 2, 0] = 1.0                                  # neck nod about the lateral axis
    for side, base, slot in (("l", 11, 3), ("r", 17, 7)):
        for i in range(3):
            M[base + i, slot, i] = 1.0                # shoulder rotation vector
        M[base + 3, slot + 1] = f[side]["elbow_axis"]  # elbow flexion
        M[base + 4, slot + 2] = f[side]["elbow_axis"]  # wrist flexion
        M[base + 5, slot + 3] = f[side]["wrist_dev_axis"]
    for side, base, slot in (("l", 23, 11), ("r", 29, 15)):
        for i in range(3):
            M[base + i, slot, i] = 1.0                # hip rotation vector
        M[base + 3, slot + 1] = f[side]["knee_axis"]   # knee flexion
        M[base + 4, slot + 2] = LATERAL                # ankle flexion
        M[base + 5, slot + 3] = f[side]["ankle_inv_axis"]
    return M


@lru_cache(maxsize=8)
def _parameter_joints(joint_rest_bytes: bytes) -> tuple:
    """``_axis_table`` as each parameter's one joint (35,) int (-1: none) and axis (35, 3):
    a parameter moves one joint, so forward kinematics need not sum the other 18's zeros."""
    M = _axis_table(joint_rest_bytes)
    moved = np.abs(M).sum(axis=2) > 0                    # (35, 19)
    assert (moved.sum(axis=1) <= 1).all(), "a parameter moves at most one joint"
    joint = np.where(moved.any(axis=1), moved.argmax(axis=1), -1).astype(np.int64)
    axis = np.ascontiguousarray(M[np.arange(PARAM_COUNT), np.maximum(joint, 0)] * (joint >= 0)[:, None])
    return joint, axis


def _rest_offsets_vector(model: BodyModel) -> np.ndarray:
    """(35,) subtracted from the parameters so that elbows and knees measure from straight."""
    f = joint_frames(model)
    off = np.zeros(PARAM_COUNT)
    off[P["l_elbow"]], off[P["r_elbow"]] = f["l"]["rest_elbow"], f["r"]["rest_elbow"]
    off[P["l_knee"]], off[P["r_knee"]] = f["l"]["rest_knee"], f["r"]["rest_knee"]
    return off


def local_rotations(model: BodyModel, params: np.ndarray) -> np.ndarray:
    """(B, 35) parameters -> (B, 16, 3, 3) rotation of each segment relative to its parent."""
    rest_offsets, param_joint, param_axis = model.kinematic_tables[:3]
    return _local_rotations(np.atleast_2d(np.asarray(params, dtype=np.float64)), rest_offsets, param_joint,
                            param_axis, _segment_mask(None))


@lru_cache(maxsize=64)
def _with_ancestors(segments: tuple) -> tuple:
    """The segments and all their ancestors, parents first."""
    need = set()
    for s in segments:
        while s >= 0 and s not in need:
            need.add(s)
            s = SEGMENT_PARENTS[s]
    return tuple(sorted(need))  # a parent's index is below its children's


@lru_cache(maxsize=256)
def _segment_mask(segments: tuple | None) -> np.ndarray:
    order = range(16) if segments is None else _with_ancestors(segments)
    mask = np.zeros(16, dtype=np.bool_)
    mask[list(order)] = True
    return mask


_SEGMENT_PARENTS = np.array(SEGMENT_PARENTS, dtype=np.int64)


def forward_kinematics(model: BodyModel, params: np.ndarray, segments: tuple | None = None) -> Pose:
    """(B, 35) or (35,) parameters -> Pose with a leading batch axis of B (1 for a single vector).

    segments: compute only these segments (and their ancestors); the others' rotations,
    origins and joints are NaN. The energies use this for the few parts that move.
    """
    p = np.atleast_2d(np.asarray(params, dtype=np.float64))
    if p.shape[1] != PARAM_COUNT:
        raise ValueError(f"expected {PARAM_COUNT} parameters, got {p.shape[1]}")
    needed = _segment_mask(None if segments is None else tuple(segments))
    rest_offsets, param_joint, param_axis, offsets, head_top_offset = model.kinematic_tables
    rot, org, joints = _forward_kinematics(p, rest_offsets, param_joint, param_axis, _SEGMENT_PARENTS, offsets,
                                           head_top_offset, needed)
    return Pose(rot, org, joints)


# ------------------------------------------- compiled kernels (numba): the energies' hot path
# Each evaluation runs forward kinematics on a handful of candidates; numpy's per-call
# overhead on (B, 16, 3, 3) stacks cost more than the arithmetic.

@njit(cache=True, nogil=True, inline="always")
def _rodrigues(x: float, y: float, z: float, out: np.ndarray) -> None:
    """Rotation vector -> out (3, 3): R = I + a [r]x + b [r]x^2, stable near zero."""
    theta2 = x * x + y * y + z * z
    if theta2 < 1e-12:
        a, b = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0
    else:
        theta = np.sqrt(theta2)
        a, b = np.sin(theta) / theta, (1.0 - np.cos(theta)) / (theta * theta)
    out[0, 0] = 1.0 - b * (y * y + z * z)
    out[1, 1] = 1.0 - b * (x * x + z * z)
    out[2, 2] = 1.0 - b * (x * x + y * y)
    bxy, bxz, byz = b * x * y, b * x * z, b * y * z
    out[0, 1], out[1, 0] = bxy - a * z, bxy + a * z
    out[0, 2], out[2, 0] = bxz + a * y, bxz - a * y
    out[1, 2], out[2, 1] = byz - a * x, byz + a * x


@njit(cache=True, nogil=True, inline="always")
def _matmul3(A: np.ndarray, B: np.ndarray, out: np.ndarray) -> None:
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True, nogil=True, inline="always")
def _rot_z(angle: float, out: np.ndarray) -> None:
    c, s = np.cos(angle), np.sin(angle)
    out[:] = 0.0
    out[0, 0], out[0, 1], out[1, 0], out[1, 1], out[2, 2] = c, -s, s, c, 1.0


@njit(cache=True, nogil=True)
def _rotvecs_to_matrices(rv: np.ndarray) -> np.ndarray:
    out = np.empty((rv.shape[0], 3, 3))
    for i in range(rv.shape[0]):
        _rodrigues(rv[i, 0], rv[i, 1], rv[i, 2], out[i])
    return out


@njit(cache=True, nogil=True)
def _matrices_to_rotvecs(R: np.ndarray) -> np.ndarray:
    out = np.empty((R.shape[0], 3))
    for i in range(R.shape[0]):
        _rotvec(R[i], out[i])
    return out


@njit(cache=True, nogil=True)
def _rotations_z(angle: np.ndarray) -> np.ndarray:
    out = np.empty((angle.shape[0], 3, 3))
    for i in range(angle.shape[0]):
        _rot_z(angle[i], out[i])
    return out


# The 19 rotation-vector joints each segment's local rotation is made of (first, count).
_SEGMENT_JOINTS = np.array([(0, 1), (1, 1), (1, 1), (2, 1), (3, 1), (4, 1), (5, 2), (7, 1), (8, 1), (9, 2),
                            (11, 1), (12, 1), (13, 2), (15, 1), (16, 1), (17, 2)], dtype=np.int64)


@njit(cache=True, nogil=True)
def _local_rotations(p: np.ndarray, rest_offsets: np.ndarray, param_joint: np.ndarray, param_axis: np.ndarray,
                     needed: np.ndarray) -> np.ndarray:
    """(B, 35) -> (B, 16, 3, 3): the 19 joint rotations (``_axis_table``) composed per segment,
    for the ``needed`` (16,) segments only (the others are left unset)."""
    B = p.shape[0]
    R = np.empty((B, 16, 3, 3))
    M = np.empty((19, 3, 3))
    Z = np.empty((3, 3))
    rv = np.zeros((19, 3))
    joint_needed = np.zeros(19, np.bool_)
    for s in range(16):
        if needed[s]:
            for k in range(_SEGMENT_JOINTS[s, 0], _SEGMENT_JOINTS[s, 0] + _SEGMENT_JOINTS[s, 1]):
                joint_needed[k] = True
    for b in range(B):
        rv[:] = 0.0
        for i in range(35):
            k = param_joint[i]
            if k >= 0 and joint_needed[k]:
                v = p[b, i] - rest_offsets[i]
                if v != 0.0:
                    for c in range(3):
                        rv[k, c] += v * param_axis[i, c]
        for k in range(19):
            if joint_needed[k]:
                _rodrigues(rv[k, 0], rv[k, 1], rv[k, 2], M[k])
        if needed[0]:
            _rot_z(p[b, 3], Z)
            _matmul3(Z, M[0], R[b, 0])
        if needed[1]:
            R[b, 1] = M[1]
        if needed[2]:
            R[b, 2] = M[1]
        if needed[3]:
            _rot_z(p[b, 10], Z)
            _matmul3(M[2], Z, R[b, 3])
        for seg, first in ((4, 3), (7, 7), (10, 11), (13, 15)):  # a limb: root, middle, end (two joints)
            if needed[seg]:
                R[b, seg] = M[first]
            if needed[seg + 1]:
                R[b, seg + 1] = M[first + 1]
            if needed[seg + 2]:
                _matmul3(M[first + 2], M[first + 3], R[b, seg + 2])
    return R


@njit(cache=True, nogil=True)
def _forward_kinematics(p, rest_offsets, param_joint, param_axis, parents, offsets, head_top_offset, needed):
    """(B, 35) -> rotations (B, 16, 3, 3), origins (B, 16, 3), joints (B, 17, 3); segments not
    ``needed`` (16,) are NaN."""
    B = p.shape[0]
    local = _local_rotations(p, rest_offsets, param_joint, param_axis, needed)
    rot = np.full((B, 16, 3, 3), np.nan)
    org = np.full((B, 16, 3), np.nan)
    joints = np.full((B, 17, 3), np.nan)
    for b in range(B):
        for s in range(16):  # a parent's index is below its children's
            if not needed[s]:
                continue
            parent = parents[s]
            if parent < 0:
                rot[b, s] = local[b, s]
                org[b, s] = p[b, 0:3]
            else:
                _matmul3(rot[b, parent], local[b, s], rot[b, s])
                for i in range(3):
                    org[b, s, i] = org[b, parent, i] + (rot[b, parent, i, 0] * offsets[s, 0] + rot[b, parent, i, 1]
                                                        * offsets[s, 1] + rot[b, parent, i, 2] * offsets[s, 2])
            joints[b, s] = org[b, s]
        if needed[HEAD_TOP_SEGMENT]:
            for i in range(3):
                joints[b, 16, i] = org[b, 3, i] + (rot[b, 3, i, 0] * head_top_offset[0] + rot[b, 3, i, 1]
                                                   * head_top_offset[1] + rot[b, 3, i, 2] * head_top_offset[2])
    return rot, org, joints


# The limbs' roots: (segment, its parent, first of its 3 rotation-vector parameters)
LIMB_ROOTS = ((4, 2, 11), (7, 2, 17), (10, 0, 23), (13, 0, 29))


def hold_limbs_in_world(model: BodyModel, params: np.ndarray, reference: np.ndarray,
                        reference_rotations: np.ndarray | None = None) -> np.ndarray:
    """(B, 35) torso candidates -> the same with shoulder and hip rotations changed so that the
    upper arms and thighs keep the world orientation they have at ``reference`` (35,).
    reference_rotations: (16, 3, 3) the reference's segment rotations, when the caller has them
    (the torso's line searches call this for every batch of candidates, hence compiled).

    Moving the torso then carries the limbs along by their attachment points only, instead of
    swinging them with it: the torso and limb sub-problems decouple (no drift of the pelvis
    heading traded against hip rotations).
    """
    p = np.array(np.atleast_2d(params), dtype=np.float64)
    if reference_rotations is None:
        reference_rotations = forward_kinematics(model, reference).rotations[0]
    _hold_limbs(p, np.ascontiguousarray(reference_rotations, dtype=np.float64), _LIMB_ROOTS)
    return p


_LIMB_ROOTS = np.array(LIMB_ROOTS, dtype=np.int64)


@njit(cache=True, nogil=True)
def _hold_limbs(p: np.ndarray, reference_rotations: np.ndarray, limb_roots: np.ndarray) -> None:
    """In place on (B, 35): each limb root's rotation vector = parent^T @ its reference rotation,
    the parent (pelvis or chest) posed by the candidate's own root and spine parameters."""
    tilt, spine, pelvis, chest = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Z, local = np.empty((3, 3)), np.empty((3, 3))
    for b in range(p.shape[0]):
        _rot_z(p[b, 3], Z)
        _rodrigues(p[b, 4], p[b, 5], 0.0, tilt)
        _matmul3(Z, tilt, pelvis)
        _rodrigues(p[b, 6], p[b, 7], p[b, 8], spine)
        _matmul3(pelvis, spine, chest)
        for seg, parent_seg, first in limb_roots:
            parent = pelvis if parent_seg == 0 else chest
            for i in range(3):
                for j in range(3):
                    local[i, j] = (parent[0, i] * reference_rotations[seg, 0, j] + parent[1, i]
                                   * reference_rotations[seg, 1, j] + parent[2, i] * reference_rotations[seg, 2, j])
            _rotvec(local, p[b, first:first + 3])


@njit(cache=True, nogil=True, inline="always")
def _rotvec(R: np.ndarray, out: np.ndarray) -> None:
    """(3, 3) rotation -> out (3,), angle in [0, pi], through the quaternion by Shepperd's
    method: of the four formulas, the one of the largest diagonal element (numerically safe)."""
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)
    choice, largest = 3, trace
    for i in range(3):
        if R[i, i] > largest:
            choice, largest = i, R[i, i]
    if choice == 0:
        q[0], q[1], q[2], q[3] = 1.0 - trace + 2.0 * R[0, 0], R[1, 0] + R[0, 1], R[2, 0] + R[0, 2], R[2, 1] - R[1, 2]
    elif choice == 1:
        q[0], q[1], q[2], q[3] = R[0, 1] + R[1, 0], 1.0 - trace + 2.0 * R[1, 1], R[2, 1] + R[1, 2], R[0, 2] - R[2, 0]
    elif choice == 2:
        q[0], q[1], q[2], q[3] = R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], 1.0 - trace + 2.0 * R[2, 2], R[1, 0] - R[0, 1]
    else:
        q[0], q[1], q[2], q[3] = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1.0 + trace
    norm = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[3] < 0:
        norm = -norm
    for i in range(4):
        q[i] /= norm
    sin_half = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
    angle = 2.0 * np.arctan2(sin_half, q[3])
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
    else:
        scale = angle / np.sin(angle / 2.0)
    for i in range(3):
        out[i] = scale * q[i]


def rest_params(model: BodyModel, position=None, heading: float = 0.0) -> np.ndarray:
    """(35,) the rest pose (A-pose arms, straight legs) at ``position`` (pelvis), turned by heading."""
    p = np.zeros(PARAM_COUNT)
    p[0:3] = model.joint_rest[0] if position is None else position
    p[3] = heading
    f = joint_frames(model)
    p[P["l_elbow"]], p[P["r_elbow"]] = f["l"]["rest_elbow"], f["r"]["rest_elbow"]
    p[P["l_knee"]], p[P["r_knee"]] = f["l"]["rest_knee"], f["r"]["rest_knee"]
    return p


def clip_to_limits(params: np.ndarray) -> np.ndarray:
    """(..., 35) parameters clipped into the joint limits."""
    return np.clip(params, PARAM_LIMITS[:, 0], PARAM_LIMITS[:, 1])


# Each limb parameter's sign in the limb's mirror image (a reflection through the body's
# sagittal plane; x is lateral in every joint frame): a rotation vector keeps its x and flips
# y and z, a hinge keeps its angle. Checked by forward kinematics in tests/test_body.py.
MIRROR_SIGNS = {
    "arm": {"shoulder_x": 1.0, "shoulder_y": -1.0, "shoulder_z": -1.0, "elbow": 1.0, "wrist_flex": 1.0,
            "wrist_dev": -1.0},
    "leg": {"hip_x": 1.0, "hip_y": -1.0, "hip_z": -1.0, "knee": 1.0, "ankle_flex": 1.0, "ankle_inv": -1.0},
}


def swap_sides(params: np.ndarray, limb: str) -> np.ndarray:
    """(35,) -> (35,): the left and right ``limb`` ("arm" or "leg") exchanged, each taking the
    mirror image of the other's pose. Seen from the side the two are alike (a stride with the
    left foot ahead or the right), so a silhouette fit can settle on the wrong one."""
    if limb not in MIRROR_SIGNS:
        raise ValueError(f"limb must be one of {sorted(MIRROR_SIGNS)}, got {limb!r}")
    out = np.array(params, dtype=np.float64)
    for name, sign in MIRROR_SIGNS[limb].items():
        left, right = P[f"l_{name}"], P[f"r_{name}"]
        out[left], out[right] = sign * params[right], sign * params[left]
    return out


def joints_dict(joints: np.ndarray) -> dict:
    """(17, 3) -> {joint name: [x, y, z]} (plain floats, for JSON)."""
    return {name: [float(v) for v in joints[i]] for i, name in enumerate(JOINT_NAMES)}


def skinned_vertices(model: BodyModel, pose: Pose, index: int = 0) -> np.ndarray:
    """(V, 3) world vertices of the smoothly skinned surface (linear blend skinning)."""
    rot, org = pose.rotations[index], pose.origins[index]
    rest_origin = model.joint_rest[:16]
    local = model.vertices[:, None, :] - rest_origin[None]            # (V, 16, 3)
    per_seg = np.einsum("sij,vsj->vsi", rot, local) + org[None]         # (V, 16, 3)
    return np.einsum("vs,vsi->vi", model.skin_weights, per_seg)


def rigid_vertices(model: BodyModel, pose: Pose, index: int = 0) -> np.ndarray:
    """(V, 3) world vertices, each moving rigidly with its own segment."""
    seg = model.vertex_segment.astype(np.int64)
    local = model.vertices - model.joint_rest[seg]
    return np.einsum("vij,vj->vi", pose.rotations[index][seg], local) + pose.origins[index][seg]
