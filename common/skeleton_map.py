"""Which BVH joint plays which body role, by name and hierarchy; units and axes of a BVH skeleton.

Roles (strings): pelvis, spine_lower, spine_upper (chest), neck (base of the neck), head,
head_end (top of the head), and per side s in l, r: s_clavicle*, s_shoulder (upper-arm ball
joint), s_elbow, s_wrist, s_hand_end* (finger tips), s_hip, s_knee, s_ankle, s_toe*
(* optional).

A mapping is ``dict[role, int]``: an index below J is a joint, ``J + e`` is End Site e (End
Sites only ever stand for head_end, s_hand_end and, when a joint map says so, s_toe). Use
``point_positions``, ``role_trajectories`` or ``role_rest_positions`` rather than indexing
(F, J, 3) arrays with it.

How roles are found: the wrist, ankle and head by name (``LeftHand``, ``Bip01 L Hand``,
``hand_l``, ``LeftWrist`` ...); then the hierarchy decides the rest. Going up from the wrist,
joints that sit at the same rest position (zero OFFSET) count as one site and twist/roll joints
are skipped: the first site is the elbow, the next the shoulder (upper arm), and a next site
holding a same-side joint is the clavicle. So ``LeftShoulder`` is the clavicle in CMU and
Mixamo skeletons and the shoulder in simple ones. The chest is where the arms and neck branch.

One module of about 510 lines: the mapping of every supported skeleton onto ours.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from common.bvh import BvhMotion, bvh_global_transforms, end_site_positions, rest_positions
from common.errors import InputFileError, UserError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

SIDES = ("l", "r")
CENTRE_ROLES = ("pelvis", "spine_lower", "spine_upper", "neck", "head", "head_end")
SIDE_ROLES = ("clavicle", "shoulder", "elbow", "wrist", "hand_end", "hip", "knee", "ankle", "toe")
OPTIONAL_SIDE_ROLES = ("clavicle", "hand_end", "toe")
ROLES = CENTRE_ROLES + tuple(f"{s}_{r}" for s in SIDES for r in SIDE_ROLES)
OPTIONAL_ROLES = tuple(f"{s}_{r}" for s in SIDES for r in OPTIONAL_SIDE_ROLES)
REQUIRED_ROLES = tuple(r for r in ROLES if r not in OPTIONAL_ROLES)
END_SITE_SUFFIX = "/end"  # in a joint map: "Head/end" = the End Site of joint Head
END_SITE_ROLES = ("head_end", "hand_end", "toe")  # role name endings that may be End Sites

# Units: a human's hip-to-ankle length (thigh + shin along the joints) and standing height,
# and the length units BVH files come in; a guess within UNIT_SNAP of one of them snaps to it.
LEG_LENGTH = 0.86  # metres, hip joint centre to ankle for a 1.75 m adult
BODY_HEIGHT = 1.75  # metres
KNOWN_UNITS = {  # metres per file unit
    "m": 1.0, "cm": 0.01, "mm": 0.001, "inch": 0.0254, "foot": 0.3048,
    "cmu": 0.0254 / 0.45,  # CMU ASF/cgspeed BVH: lengths in (1/0.45) inch
}
UNIT_SNAP = 1.3  # ratio; the known units are at least 2.2x apart
UP_SAMPLE_FRAMES = 100  # frames looked at to find the up axis

_PREFIX_WORDS = {"bip", "biped", "mixamorig", "character", "def", "org", "mch"}
_FINGER = ("thumb", "index", "middle", "ring", "pink", "little", "finger", "digit", "carpal")
_END_WORDS = {"end", "nub", "tip", "top", "site"}
_TWIST = ("twist", "roll")
_NOT_HEAD = ("jaw", "eye", "brow", "lid", "lip", "tongue", "teeth", "ear", "nose")
_ELBOW = ("elbow", "forearm", "lowerarm", "lowarm", "radius", "ulna")
_KNEE = ("knee", "calf", "shin", "lowerleg", "lowleg", "tibia")
_LIMB_WORDS = {
    "clavicle", "collar", "shoulder", "humerus", "arm", "uparm", "upperarm", "elbow", "forearm", "radius",
    "ulna", "wrist", "hand", "fingers", "thumb", "hip", "hipjoint", "femur", "thigh", "upleg", "leg", "knee",
    "tibia", "shin", "calf", "ankle", "foot", "heel", "toe", "toes", "ball",
}
_WORD_RE = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")


def name_parts(name: str) -> tuple[str | None, tuple[str, ...]]:
    """A joint name -> (side "l"/"r"/None, its other words: lower case, no prefix, no digits).

    ``mixamorig:LeftForeArm`` -> ("l", ("fore", "arm")); ``Bip01 R Calf`` -> ("r", ("calf",));
    ``upperarm_twist_01_l`` -> ("l", ("upperarm", "twist")); ``LHipJoint`` -> ("l", ("hip", "joint")).
    """
    base = name.rsplit(":", 1)[-1]
    words = []
    for part in re.split(r"[\s_.\-|]+", base):
        words += [w.lower() for w in _WORD_RE.findall(part)]
    while words and (words[0] in _PREFIX_WORDS or words[0].isdigit()):
        words.pop(0)
    sides = set()
    body = []
    for w in words:
        if w in ("l", "left"):
            sides.add("l")
        elif w in ("r", "right"):
            sides.add("r")
        elif w.isdigit():
            continue
        elif w.startswith(("left", "right")) and len(w) > 5:  # all-lower names: "leftarm"
            side = "l" if w.startswith("left") else "r"
            sides.add(side)
            body.append(w[4:] if side == "l" else w[5:])
        elif w[0] in "lr" and w[1:] in _LIMB_WORDS:  # Acclaim/CMU ASF names: "lhumerus", "rfoot"
            sides.add(w[0])
            body.append(w[1:])
        else:
            body.append(w)
    side = sides.pop() if len(sides) == 1 else None
    return side, tuple(body)


class _Skeleton:
    """Hierarchy facts used by the mapping: names split, depths, sites of coincident joints."""

    def __init__(self, motion: BvhMotion):
        self.m = motion
        self.J = motion.num_joints
        self.parents = [int(p) for p in motion.parents]
        self.parts = [name_parts(n) for n in motion.names]
        self.side = [p[0] for p in self.parts]
        self.body = ["".join(p[1]) for p in self.parts]
        self.words = [set(p[1]) for p in self.parts]
        self.rest, self.rest_ends = rest_positions(motion)
        lengths = np.linalg.norm(motion.offsets, axis=1)
        self.zero = lengths <= 1e-4 * float(lengths.max(initial=0.0))  # joint sits where its parent does
        self.depth = []
        self.kids: list[list[int]] = [[] for _ in range(self.J)]
        for j, p in enumerate(self.parents):
            self.depth.append(0 if p < 0 else self.depth[p] + 1)
            if p >= 0:
                self.kids[p].append(j)

    def ancestors(self, j: int) -> list[int]:
        """Strict ancestors of j, nearest first."""
        out = []
        while self.parents[j] >= 0:
            j = self.parents[j]
            out.append(j)
        return out

    def is_ancestor(self, a: int, j: int) -> bool:
        return a in self.ancestors(j)

    def descendants(self, j: int) -> list[int]:
        out, stack = [], list(self.kids[j])
        while stack:
            k = stack.pop()
            out.append(k)
            stack += self.kids[k]
        return out

    def twist(self, j: int) -> bool:
        return any(t in self.body[j] for t in _TWIST)

    def finger(self, j: int) -> bool:
        return any(t in self.body[j] for t in _FINGER)

    def end_word(self, j: int) -> bool:
        return bool(self.words[j] & _END_WORDS)

    def sites_above(self, j: int) -> list[list[int]]:
        """Groups of coincident joints on the way up from j (j's own group excluded), each
        deepest first and without twist/roll joints; groups of only twist joints are dropped."""
        chain = [j] + self.ancestors(j)
        groups, cur = [], []
        for k, joint in enumerate(chain):
            cur.append(joint)
            if not self.zero[joint] or k == len(chain) - 1:
                groups.append(cur)
                cur = []
        out = []
        for g in groups[1:]:
            g = [x for x in g if not self.twist(x)]
            if g:
                out.append(g)
        return out

    def lca(self, joints: list[int]) -> int:
        common = None
        for j in joints:
            line = [j] + self.ancestors(j)
            common = line if common is None else [a for a in common if a in line]
        return common[0] if common else -1

    def find(self, side, test, among=None) -> list[int]:
        """Joints of `side` passing `test`, shallowest first."""
        among = range(self.J) if among is None else among
        return sorted((j for j in among if self.side[j] == side and test(j)), key=lambda j: self.depth[j])


def _limb(sk: _Skeleton, side: str, end_words, end_start: str, is_mid, end=None, mid=None) -> dict:
    """Wrist/ankle by name, then elbow/knee, shoulder/hip and clavicle by hierarchy.

    Returns {"end", "mid", "root", "girdle"} (those found). end_words: substrings that name the
    end joint ("wrist"); end_start: its fallback name start ("hand"); is_mid(j): the joint is
    named as the middle one (elbow, knee), which lets the chain skip unnamed helper joints.
    end, mid: joints already fixed by the user, used instead of searching.
    """
    def plain(j):
        return not (sk.finger(j) or sk.end_word(j) or sk.twist(j))
    if end is None:
        ends = sk.find(side, lambda j: plain(j) and any(w in sk.body[j] for w in end_words))
        ends = ends or sk.find(side, lambda j: plain(j) and sk.body[j].startswith(end_start))
        end = ends[0] if ends else None
    if mid is None and end is not None:
        sites = sk.sites_above(end)
        named = [g for g in sites if any(is_mid(x) for x in g)]
        group = named[0] if named else (sites[0] if sites else [])
        mid = ([x for x in group if is_mid(x)] or group or [None])[0]
    out = {k: v for k, v in (("end", end), ("mid", mid)) if v is not None}
    if mid is not None:
        up = sk.sites_above(mid)
        if up:
            out["root"] = up[0][0]
        same_side = [x for x in up[1] if sk.side[x] == side] if len(up) > 1 else []
        if same_side:
            out["girdle"] = same_side[0]
    return out


def _farthest_end(sk: _Skeleton, j: int, skip) -> int | None:
    """The joint or End Site below j farthest from it at rest; subtrees of joints passing
    skip(k) are left out. None when j has nothing below it."""
    below, stack = [], [k for k in sk.kids[j] if not skip(k)]
    while stack:
        k = stack.pop()
        below.append(k)
        stack += [c for c in sk.kids[k] if not skip(c)]
    pts = [(k, sk.rest[k]) for k in below]
    owners = set(below) | {j}
    pts += [(sk.J + e, sk.rest_ends[e]) for e, p in enumerate(sk.m.end_site_parents) if int(p) in owners]
    if not pts:
        return None
    return max(pts, key=lambda kp: float(np.linalg.norm(kp[1] - sk.rest[j])))[0]


def _map_side(sk: _Skeleton, s: str, roles: dict[str, int], fixed: dict[str, int]):
    arm = _limb(sk, s, ("wrist",), "hand", lambda j: any(w in sk.body[j] for w in _ELBOW),
                fixed.get(f"{s}_wrist"), fixed.get(f"{s}_elbow"))
    leg = _limb(sk, s, ("ankle",), "foot", lambda j: sk.body[j] == "leg" or any(w in sk.body[j] for w in _KNEE),
                fixed.get(f"{s}_ankle"), fixed.get(f"{s}_knee"))
    for key, role in (("end", "wrist"), ("mid", "elbow"), ("root", "shoulder"), ("girdle", "clavicle")):
        if key in arm:
            roles[f"{s}_{role}"] = fixed.get(f"{s}_{role}", arm[key])
    for key, role in (("end", "ankle"), ("mid", "knee"), ("root", "hip")):
        if key in leg:
            roles[f"{s}_{role}"] = fixed.get(f"{s}_{role}", leg[key])
    wrist, ankle = roles.get(f"{s}_wrist"), roles.get(f"{s}_ankle")
    if wrist is not None:  # finger tips: the farthest point below the wrist, thumbs aside
        hand_end = _farthest_end(sk, wrist, lambda j: "thumb" in sk.body[j])
        if hand_end is not None:
            roles[f"{s}_hand_end"] = hand_end
    if ankle is not None:  # a "toe"/"ball" joint, else the ankle's only child joint
        below = sk.descendants(ankle)
        toes = sk.find(s, lambda j: ("toe" in sk.body[j] or "ball" in sk.body[j]) and not sk.end_word(j), below)
        kids = [k for k in sk.kids[ankle] if not sk.end_word(k)]
        if toes or len(kids) == 1:
            roles[f"{s}_toe"] = (toes or kids)[0]


def _map_centre(sk: _Skeleton, roles: dict[str, int], fixed: dict[str, int]):
    heads = [fixed["head"]] if "head" in fixed else sk.find(
        None, lambda j: "head" in sk.body[j] and not sk.end_word(j) and not any(w in sk.body[j] for w in _NOT_HEAD))
    if not heads:
        return
    head = roles["head"] = heads[0]
    # the top: a "HeadTop_End"/"HeadNub" joint, else the farthest point below the head
    tops = sorted((k for k in sk.descendants(head) if sk.end_word(k) and not sk.zero[k]
                   and not any(w in sk.body[k] for w in _NOT_HEAD)), key=lambda k: sk.depth[k])
    top = tops[0] if tops else _farthest_end(sk, head, lambda k: any(w in sk.body[k] for w in _NOT_HEAD))
    if top is not None:
        roles["head_end"] = top
    root_to_head = list(reversed(sk.ancestors(head)))
    necks = [j for j in root_to_head if "neck" in sk.body[j]]
    above_head = sk.sites_above(head)
    neck = fixed.get("neck", necks[0] if necks else (above_head[0][0] if above_head else None))
    if neck is None:
        return
    roles["neck"] = neck
    shoulders = [roles[f"{s}_shoulder"] for s in SIDES if f"{s}_shoulder" in roles]
    chest = fixed.get("spine_upper", sk.lca(shoulders + [neck]))
    if chest in (neck, -1):  # the arms hang from the neck (3ds Max Biped): chest is below it
        above_neck = sk.sites_above(neck)
        chest = above_neck[0][0] if above_neck else -1
    if chest < 0:
        return
    roles["spine_upper"] = chest
    named = [j for j in root_to_head if sk.side[j] is None and sk.is_ancestor(j, chest)
             and (sk.body[j] in ("hips", "hip") or "pelvis" in sk.body[j])]
    hips = [roles[f"{s}_hip"] for s in SIDES if f"{s}_hip" in roles]
    pelvis = fixed.get("pelvis", named[-1] if named else (sk.lca(hips + [chest]) if hips else -1))
    if pelvis < 0 or pelvis == chest:
        return
    roles["pelvis"] = pelvis
    # the lowest site strictly between pelvis and chest; else a zero-length joint at the pelvis
    between = [g for g in sk.sites_above(chest) if pelvis not in g and sk.is_ancestor(pelvis, g[-1])]
    if between:
        roles["spine_lower"] = between[-1][0]
    else:
        at_pelvis = [x for x in sk.ancestors(chest) if sk.is_ancestor(pelvis, x)]
        if at_pelvis:
            roles["spine_lower"] = at_pelvis[-1]


def _auto_map(sk: _Skeleton, fixed: dict[str, int]) -> dict[str, int]:
    """Every role found; `fixed` (role -> index, from the user) anchors the search and wins."""
    roles: dict[str, int] = {}
    for s in SIDES:
        _map_side(sk, s, roles, fixed)
    _map_centre(sk, roles, fixed)
    roles = _drop_crossed(sk, roles)
    roles.update(fixed)
    return roles


def _drop_crossed(sk: _Skeleton, roles: dict[str, int]) -> dict[str, int]:
    """Drops side roles that also lie on the other side's limb or on the head's path."""
    def chain(role):
        j = roles.get(role)
        return set() if j is None or j >= sk.J else {j, *sk.ancestors(j)}
    out = dict(roles)
    for s, o in (("l", "r"), ("r", "l")):
        other = chain(f"{o}_wrist") | chain(f"{o}_ankle") | chain("head")
        for r in ("clavicle", "shoulder", "elbow", "wrist", "hip", "knee", "ankle"):
            if roles.get(f"{s}_{r}") in other:
                out.pop(f"{s}_{r}", None)
    return out


def _resolve(motion: BvhMotion, role: str, name: str, source: str) -> int:
    joint = name[: -len(END_SITE_SUFFIX)] if name.endswith(END_SITE_SUFFIX) else name
    try:
        j = motion.joint_index(joint)
    except KeyError:
        raise UserError(f"{source}: role {role} names joint {joint!r}, which {motion.source or 'the BVH'} "
                        f"does not have (joints: {', '.join(motion.names)})") from None
    if joint == name:
        return j
    ends = np.flatnonzero(motion.end_site_parents == j)
    if len(ends) == 0:
        raise UserError(f"{source}: role {role} names {name!r} but joint {joint!r} has no End Site")
    return motion.num_joints + int(ends[0])


def map_skeleton(motion: BvhMotion, overrides: dict[str, str] | None = None,
                 overrides_source: str = "--joint-map") -> dict[str, int]:
    """Role -> point index (joint j < J, or J + e for End Site e) for every role found.

    overrides: role -> joint name (``NAME/end`` for NAME's End Site), e.g. from load_joint_map;
    they win over the automatic choice. Raises UserError naming the required roles that
    could not be mapped; optional roles are simply left out.
    """
    fixed = {}
    for role, name in (overrides or {}).items():
        if role not in ROLES:
            raise UserError(f"{overrides_source}: unknown role {role!r} (roles: {', '.join(ROLES)})")
        fixed[role] = _resolve(motion, role, name, overrides_source)
        if fixed[role] >= motion.num_joints and not role.endswith(END_SITE_ROLES):
            raise UserError(f"{overrides_source}: role {role} must be a joint; only "
                            f"{', '.join(END_SITE_ROLES)} roles may name an End Site")
    roles = _auto_map(_Skeleton(motion), fixed)
    missing = [r for r in REQUIRED_ROLES if r not in roles]
    if missing:
        raise UserError(
            f"{motion.source or 'BVH'}: cannot tell which joint is {', '.join(missing)} "
            f"(joints: {', '.join(motion.names)}); name them in a --joint-map TOML file: "
            f"[joints] {missing[0]} = \"JointName\"")
    return {r: roles[r] for r in ROLES if r in roles}


def load_joint_map(path) -> dict[str, str]:
    """Reads a joint map TOML: ``[joints]`` with ``role = "JointName"`` lines -> dict[role, name]."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise InputFileError(path, f"cannot read: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputFileError(path, f"not valid TOML ({e})") from None
    table = doc.get("joints")
    if not isinstance(table, dict):
        raise InputFileError(path, "needs a [joints] table of role = \"JointName\" lines")
    out = {}
    for role, name in table.items():
        if role not in ROLES:
            raise InputFileError(path, f"joints.{role}: unknown role (roles: {', '.join(ROLES)})")
        if not isinstance(name, str) or not name:
            raise InputFileError(path, f"joints.{role}: must be a joint name in quotes")
        out[role] = name
    return out


def joint_label(motion: BvhMotion, index: int) -> str:
    """A mapping index as a name: the joint's, or ``NAME/end`` for an End Site."""
    if index < motion.num_joints:
        return motion.names[index]
    return motion.names[int(motion.end_site_parents[index - motion.num_joints])] + END_SITE_SUFFIX


# ---------------------------------------------------------------------------------------------
# Units and axes


def point_positions(motion: BvhMotion, frames=None) -> np.ndarray:
    """Joints then End Sites, (F, J + E, 3) in file units: what mapping indices index."""
    pos, rot = bvh_global_transforms(motion, frames)
    return np.concatenate([pos, end_site_positions(motion, transforms=(pos, rot))], axis=1)


def _rest_points(motion: BvhMotion) -> np.ndarray:
    joints, ends = rest_positions(motion)
    return np.concatenate([joints, ends])


def _partial_map(motion: BvhMotion) -> dict[str, int]:
    """The roles that can be found automatically, without complaint about the others."""
    return _auto_map(_Skeleton(motion), {})


def guess_units(motion: BvhMotion, mapping: dict[str, int] | None = None) -> float:
    """Metres per file unit, from the hip-knee-ankle bone lengths (or, when the legs cannot be
    mapped, the largest extent of the rest pose taken as body height). A guess within a factor
    UNIT_SNAP of a KNOWN_UNITS value returns that value exactly (CMU: 0.056444)."""
    mapping = mapping if mapping is not None else _partial_map(motion)
    rest = _rest_points(motion)
    legs = []
    for s in SIDES:
        if all(f"{s}_{r}" in mapping for r in ("hip", "knee", "ankle")):
            h, k, a = (rest[mapping[f"{s}_{r}"]] for r in ("hip", "knee", "ankle"))
            legs.append(np.linalg.norm(k - h) + np.linalg.norm(a - k))
    if legs and np.mean(legs) > 0:
        guess = LEG_LENGTH / float(np.mean(legs))
    else:
        extent = float(np.max(rest.max(axis=0) - rest.min(axis=0))) if len(rest) else 0.0
        if extent <= 0:
            raise UserError(f"{motion.source or 'BVH'}: skeleton has no extent; cannot guess its units")
        guess = BODY_HEIGHT / extent
    nearest = min(KNOWN_UNITS.values(), key=lambda u: abs(np.log(guess / u)))
    return nearest if abs(np.log(guess / nearest)) <= np.log(UNIT_SNAP) else guess


_AXES = {"+x": (0, 1), "-x": (0, -1), "+y": (1, 1), "-y": (1, -1), "+z": (2, 1), "-z": (2, -1)}


def guess_up_axis(motion: BvhMotion, mapping: dict[str, int] | None = None) -> str:
    """The file's up axis, "+y" (most BVH, CMU), "+z", ...: the axis nearest the median
    ankles-to-head direction over the clip (the rest pose when there are no frames).
    Without a mapping of head and ankles it returns "+y", the BVH convention."""
    mapping = mapping if mapping is not None else _partial_map(motion)
    need = ("head", "l_ankle", "r_ankle")
    if not all(r in mapping for r in need):
        return "+y"
    if motion.num_frames:
        count = min(UP_SAMPLE_FRAMES, motion.num_frames)
        pts = point_positions(motion, np.unique(np.linspace(0, motion.num_frames - 1, count).astype(int)))
    else:
        pts = _rest_points(motion)[None]
    up = pts[:, mapping["head"]] - 0.5 * (pts[:, mapping["l_ankle"]] + pts[:, mapping["r_ankle"]])
    up = np.median(up / np.maximum(np.linalg.norm(up, axis=1, keepdims=True), 1e-12), axis=0)
    axis = int(np.argmax(np.abs(up)))
    return ("+" if up[axis] >= 0 else "-") + "xyz"[axis]


def up_axis_rotation(up_axis: str) -> np.ndarray:
    """(3, 3) proper rotation taking the file's axes to ours (that axis -> +z). "+y" -> x stays,
    y -> z, z -> -y (a +90 deg turn about x), so handedness and left/right are kept."""
    key = up_axis if up_axis[:1] in "+-" else "+" + up_axis
    if key.lower() not in _AXES:
        raise UserError(f"up axis must be one of {', '.join(_AXES)}, not {up_axis!r}")
    axis, sign = _AXES[key.lower()]
    up = np.zeros(3)
    up[axis] = sign
    z = np.array([0.0, 0.0, 1.0])
    if abs(up[2]) == 1.0:  # +z: identity; -z: half turn about x
        return np.diag([1.0, up[2], up[2]])
    k = np.cross(up, z)  # unit, since up is perpendicular to z: a quarter turn about k
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + K + K @ K


def _world(motion, mapping, metres_per_unit, up_axis):
    mapping = mapping if mapping is not None else map_skeleton(motion)
    scale = guess_units(motion, mapping) if metres_per_unit is None else float(metres_per_unit)
    W = up_axis_rotation(guess_up_axis(motion, mapping) if up_axis is None else up_axis)
    return mapping, scale, W


def role_trajectories(motion: BvhMotion, mapping: dict[str, int] | None = None, frames=None, *,
                      metres_per_unit: float | None = None, up_axis: str | None = None) -> dict[str, np.ndarray]:
    """Role -> (F, 3) world positions in metres, z up (the file's axes turned so its up axis is
    +z; heading left as in the file). Units and up axis are guessed unless given.
    frames: None (all), an int, a slice, or (K,) int indices."""
    mapping, scale, W = _world(motion, mapping, metres_per_unit, up_axis)
    pts = point_positions(motion, frames)
    return {r: scale * pts[:, i] @ W.T for r, i in mapping.items()}


def role_rotations(motion: BvhMotion, mapping: dict[str, int] | None = None, frames=None, *,
                   up_axis: str | None = None) -> dict[str, np.ndarray]:
    """Role -> (F, 3, 3) world rotation relative to the rest pose, in the z-up world of
    role_trajectories: a bone vector v of the rest pose (role_rest_positions differences,
    below that joint) is ``R @ v`` at the frame. An End Site role has its joint's rotation."""
    mapping, _, W = _world(motion, mapping, 1.0, up_axis)
    _, rot = bvh_global_transforms(motion, frames)
    J = motion.num_joints
    out = {}
    for r, i in mapping.items():
        j = i if i < J else int(motion.end_site_parents[i - J])
        out[r] = W @ rot[:, j] @ W.T
    return out


def role_rest_positions(motion: BvhMotion, mapping: dict[str, int] | None = None, *,
                        metres_per_unit: float | None = None, up_axis: str | None = None) -> dict[str, np.ndarray]:
    """Role -> (3,) position in the HIERARCHY pose (all OFFSETs, no rotation), metres, z up,
    with the root joint at its OFFSET."""
    mapping, scale, W = _world(motion, mapping, metres_per_unit, up_axis)
    rest = _rest_points(motion)
    return {r: scale * W @ rest[i] for r, i in mapping.items()}
