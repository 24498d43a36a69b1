"""BVH motion files: read, write, forward kinematics. Pure functions on numpy arrays.

Conventions (those of the Biovision format as Blender, MotionBuilder and the CMU conversions use
it):
- Angles in the file are degrees. For a joint whose channels list ``Zrotation Xrotation
  Yrotation`` the local rotation is ``Rz @ Rx @ Ry`` (column vectors, each channel applied in the
  order listed, i.e. intrinsic Euler angles); any order and any subset of channels is allowed.
- A joint's local translation is its OFFSET, except for the components that it has position
  channels for: those come from the channel values. The OFFSET is then the rest (bind) value,
  which is what Blender and MotionBuilder write (CMU roots have a zero OFFSET, so it makes no
  difference there).
- ``global_R[j] = global_R[parent] @ local_R[j]`` and
  ``global_p[j] = global_p[parent] + global_R[parent] @ local_t[j]``.
- Positions are in the file's own units and axes; ``common.skeleton_map`` converts to metres,
  z up.
"""
from __future__ import annotations

import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.errors import FieldChecks, InputFileError

POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
_CHANNEL_BY_LOWER = {c.lower(): c for c in POSITION_CHANNELS + ROTATION_CHANNELS}
VALUE_FORMAT = "%.6f"  # written channel values and offsets: 1e-6 file units, ample for mm data
MAX_DEPTH = 200  # joints nested in joints; skeletons have 10-30 levels (a hand's fingers included)
_WHOLE = re.compile(r"[0-9]+")  # a count in the file: ASCII digits (str.isdigit also takes "²")
# Frame rates that are not whole numbers, in frames per second: the NTSC video rates (N * 1000/1001).
NTSC_RATES = (24000 / 1001, 30000 / 1001, 60000 / 1001, 120000 / 1001)
# Relative distance within which a clip's rate is one of NTSC_RATES or a whole number of frames per
# second. Writers round Frame Time to 6 or 7 decimals (CMU: 0.0083333, others 0.008333 = 120.0048
# fps), up to 5e-7 s off: 6e-5 of the rate at 120 fps, 1.2e-4 at 240, 1.6e-4 at 480. Well under
# the 1e-3 between 30 and 29.97 fps, so that an NTSC rate is never taken for the whole one.
RATE_SNAP_TOLERANCE = 2e-4


def recorded_rate(frame_time: float) -> float:
    """Frames per second of a clip whose file says ``frame_time`` seconds per frame: 1 / frame_time,
    or the NTSC or whole rate within RATE_SNAP_TOLERANCE of it, since the file rounds the frame
    time (a 120 fps clip would otherwise give sequences at 30.00012 fps, a rate nobody records at).
    0 for a frame time that is not positive."""
    if not frame_time > 0:
        return 0.0
    rate = 1.0 / frame_time
    if not math.isfinite(rate):  # a frame time below 1e-308 s: nothing to snap to
        return rate
    for known in NTSC_RATES + (float(round(rate)),):
        if known > 0 and abs(rate - known) <= RATE_SNAP_TOLERANCE * known:
            return known
    return rate


def _frozen(a, dtype) -> np.ndarray:
    """A read-only view of `a` as `dtype` (no copy when the type already matches)."""
    v = np.asarray(a, dtype=dtype).view()
    v.flags.writeable = False
    return v


@dataclass(frozen=True, eq=False)
class BvhMotion:
    """A BVH skeleton and its motion, exactly as the file holds them (file units and axes).

    names: (J,) joint names, in file order (parents come before their children).
    parents: (J,) int, index of each joint's parent, -1 for a root.
    offsets: (J, 3) float, OFFSET of each joint from its parent (rest pose).
    channels: (J,) tuples of channel names per joint, e.g. ("Xposition", ..., "Zrotation").
    end_site_parents: (E,) int, the joint each End Site hangs from.
    end_site_offsets: (E, 3) float, OFFSET of each End Site from its joint.
    frame_time: seconds per frame.
    values: (F, C) float, the MOTION block; columns follow the joints' channels in order.
    source: where it came from (a path or a label), for messages.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_site_parents: np.ndarray
    end_site_offsets: np.ndarray
    frame_time: float
    values: np.ndarray
    source: str = ""

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "names", tuple(self.names))
        set_(self, "channels", tuple(tuple(c) for c in self.channels))
        set_(self, "parents", _frozen(self.parents, np.int64).reshape(-1))
        set_(self, "offsets", _frozen(self.offsets, np.float64).reshape(-1, 3))
        set_(self, "end_site_parents", _frozen(self.end_site_parents, np.int64).reshape(-1))
        set_(self, "end_site_offsets", _frozen(self.end_site_offsets, np.float64).reshape(-1, 3))
        set_(self, "values", _frozen(self.values, np.float64))
        set_(self, "frame_time", float(self.frame_time))
        n = len(self.names)
        if not (len(self.parents) == len(self.offsets) == len(self.channels) == n):
            raise ValueError("names, parents, offsets and channels must have one entry per joint")
        if len(self.end_site_parents) != len(self.end_site_offsets):
            raise ValueError("end_site_parents and end_site_offsets differ in length")
        if any(not (-1 <= p < j) for j, p in enumerate(self.parents)):
            raise ValueError("each parent must be -1 or an earlier joint")
        if any(not (0 <= p < n) for p in self.end_site_parents):
            raise ValueError("end_site_parents must index joints")
        for chans in self.channels:
            for c in chans:
                if c not in _CHANNEL_BY_LOWER.values():
                    raise ValueError(f"unknown channel {c!r}")
        if self.values.ndim != 2 or self.values.shape[1] != self.num_channels:
            raise ValueError(f"values must be (F, {self.num_channels}), not {self.values.shape}")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def num_frames(self) -> int:
        return self.values.shape[0]

    @property
    def num_channels(self) -> int:
        return sum(len(c) for c in self.channels)

    @property
    def fps(self) -> float:
        """The rate the clip was recorded at (``recorded_rate``), not 1 / the rounded Frame Time."""
        return recorded_rate(self.frame_time)

    @property
    def channel_starts(self) -> np.ndarray:
        """(J,) int: the first column of `values` that belongs to each joint."""
        return np.cumsum([0] + [len(c) for c in self.channels[:-1]], dtype=np.int64)

    def joint_index(self, name: str) -> int:
        """Index of the joint called `name` (exact match first, then case-insensitive)."""
        if name in self.names:
            return self.names.index(name)
        lower = [n.lower() for n in self.names]
        if name.lower() in lower:
            return lower.index(name.lower())
        raise KeyError(name)

    def children(self, joint: int) -> list[int]:
        return [j for j, p in enumerate(self.parents) if p == joint]


# ---------------------------------------------------------------------------------------------
# Reading


class _Tokens:
    """Whitespace tokens of the HIERARCHY part with their 1-based line numbers."""

    def __init__(self, lines: list[str], source: str):
        self.toks = [(t, i + 1) for i, line in enumerate(lines) for t in line.split()]
        self.pos = 0
        self.source = source
        self.last_line = len(lines)

    def error(self, problem: str, line: int | None = None):
        if line is None:
            line = self.toks[self.pos][1] if self.pos < len(self.toks) else self.last_line
        return InputFileError(self.source, f"line {line}: {problem}")

    def peek(self) -> str | None:
        return self.toks[self.pos][0] if self.pos < len(self.toks) else None

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.toks):
            raise self.error(f"file ends where {what} was expected")
        tok = self.toks[self.pos]
        self.pos += 1
        return tok

    def expect(self, word: str):
        tok, line = self.next(repr(word))
        if tok.upper() != word.upper():
            raise self.error(f"expected {word!r}, found {tok!r}", line)

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            x = float(tok)
        except ValueError:
            raise self.error(f"{what} must be a number, found {tok!r}", line) from None
        if not math.isfinite(x):
            raise self.error(f"{what} must be finite, found {tok!r}", line)
        return x


def _parse_joint(tk: _Tokens, parent: int, out: dict, depth: int = 0):
    """Reads the body of ROOT/JOINT after its keyword, recursively: name { OFFSET CHANNELS ... }."""
    kw_line = tk.toks[tk.pos - 1][1]
    if depth > MAX_DEPTH:
        raise tk.error(f"joints nested more than {MAX_DEPTH} deep (a '}}' missing?)", kw_line)
    name_parts = []  # a name may hold spaces ("Bip01 L Thigh") but ends with its line
    while tk.peek() not in ("{", None) and tk.toks[tk.pos][1] == kw_line:
        name_parts.append(tk.next("joint name")[0])
    name = " ".join(name_parts)
    if not name:
        raise tk.error("joint without a name", kw_line)
    if name in out["index"]:
        raise tk.error(f"duplicate joint name {name!r}", kw_line)
    tk.expect("{")
    j = len(out["names"])
    out["index"][name] = j
    out["names"].append(name)
    out["parents"].append(parent)
    out["offsets"].append(None)
    out["channels"].append(())
    seen_channels = False
    while True:
        tok, line = tk.next(f"'}}' closing joint {name!r}")
        key = tok.upper()
        if key == "OFFSET":
            if out["offsets"][j] is not None:
                raise tk.error(f"second OFFSET in joint {name!r}", line)
            out["offsets"][j] = [tk.number(f"OFFSET of {name!r}") for _ in range(3)]
        elif key == "CHANNELS":
            if seen_channels:
                raise tk.error(f"second CHANNELS in joint {name!r}", line)
            seen_channels = True
            n_tok, n_line = tk.next("channel count")
            if not _WHOLE.fullmatch(n_tok):
                raise tk.error(f"CHANNELS count must be a whole number, found {n_tok!r}", n_line)
            chans = []
            for _ in range(int(n_tok)):
                c_tok, c_line = tk.next(f"channel name of {name!r}")
                c = _CHANNEL_BY_LOWER.get(c_tok.lower())
                if c is None:
                    raise tk.error(f"unknown channel {c_tok!r} in joint {name!r} (CHANNELS says {n_tok})", c_line)
                if c in chans:
                    raise tk.error(f"channel {c} listed twice in joint {name!r}", c_line)
                chans.append(c)
            out["channels"][j] = tuple(chans)
        elif key in ("JOINT", "ROOT"):
            if key == "ROOT":
                raise tk.error("ROOT inside a joint (use JOINT)", line)
            _parse_joint(tk, j, out, depth + 1)
        elif key == "END":
            site_line = line
            while tk.peek() not in ("{", None) and tk.toks[tk.pos][1] == site_line:  # "End Site [name]"
                tk.next("End Site")
            tk.expect("{")
            offset = None
            while True:
                t, l2 = tk.next("'}' closing End Site")
                if t == "}":
                    break
                if t.upper() != "OFFSET" or offset is not None:
                    raise tk.error(f"End Site of {name!r} may only hold one OFFSET, found {t!r}", l2)
                offset = [tk.number(f"End Site OFFSET of {name!r}") for _ in range(3)]
            if offset is None:
                raise tk.error(f"End Site of {name!r} has no OFFSET", site_line)
            out["end_parents"].append(j)
            out["end_offsets"].append(offset)
        elif tok == "}":
            break
        else:
            raise tk.error(f"unexpected {tok!r} in joint {name!r}", line)
    if out["offsets"][j] is None:
        raise tk.error(f"joint {name!r} has no OFFSET", kw_line)


_FRAMES_RE = re.compile(r"^\s*frames\s*:\s*(\S+)\s*$", re.IGNORECASE)
_FRAME_TIME_RE = re.compile(r"^\s*frame\s+time\s*:\s*(\S+)\s*$", re.IGNORECASE)


def parse_bvh(text: str, source: str = "<bvh>") -> BvhMotion:
    """Parses BVH text. Errors: InputFileError(source, "line N: ...")."""
    lines = text.lstrip("\ufeff").splitlines()
    motion_at = next((i for i, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    if motion_at is None:
        raise InputFileError(source, f"line {len(lines)}: no MOTION section")
    tk = _Tokens(lines[:motion_at], source)
    if tk.peek() is None or tk.peek().upper() != "HIERARCHY":
        raise tk.error("file must start with HIERARCHY")
    tk.next("HIERARCHY")
    out = dict(names=[], parents=[], offsets=[], channels=[], end_parents=[], end_offsets=[], index={})
    while tk.peek() is not None:
        tok, line = tk.next("ROOT")
        if tok.upper() != "ROOT":
            raise tk.error(f"expected ROOT, found {tok!r}", line)
        _parse_joint(tk, -1, out)
    if not out["names"]:
        raise tk.error("HIERARCHY holds no ROOT joint", motion_at + 1)

    # MOTION header: "Frames: N" and "Frame Time: t" on the next non-blank lines.
    rest = [(i + 1, line) for i, line in enumerate(lines[motion_at + 1:], start=motion_at + 1) if line.strip()]
    header = {}
    for key, regex in (("frames", _FRAMES_RE), ("frame_time", _FRAME_TIME_RE)):
        if not rest:
            raise InputFileError(source, f"line {len(lines)}: file ends before the MOTION header's {key}")
        line_no, line = rest.pop(0)
        m = regex.match(line)
        want = "Frames: N" if key == "frames" else "Frame Time: SECONDS"
        if not m:
            raise InputFileError(source, f"line {line_no}: expected '{want}', found {line.strip()[:40]!r}")
        header[key] = (m.group(1), line_no)
    n_tok, n_line = header["frames"]
    if not _WHOLE.fullmatch(n_tok):
        raise InputFileError(source, f"line {n_line}: Frames must be a whole number, found {n_tok!r}")
    n_frames = int(n_tok)
    t_tok, t_line = header["frame_time"]
    try:
        frame_time = float(t_tok)
    except ValueError:
        raise InputFileError(source, f"line {t_line}: Frame Time must be a number, found {t_tok!r}") from None
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise InputFileError(source, f"line {t_line}: Frame Time must be positive, found {t_tok!r}")

    n_chan = sum(len(c) for c in out["channels"])
    if len(rest) != n_frames:
        at = rest[n_frames][0] if len(rest) > n_frames else len(lines)
        raise InputFileError(
            source, f"line {at}: Frames: {n_frames} (line {n_line}) but {len(rest)} frame lines follow")
    split = [line.split() for _, line in rest]
    for (line_no, _), toks in zip(rest, split):
        if len(toks) != n_chan:
            raise InputFileError(source, f"line {line_no}: {len(toks)} values, the hierarchy has {n_chan} channels")
    try:
        values = np.array(list(itertools.chain.from_iterable(split)), dtype=np.float64)
    except ValueError:
        values = None
    if values is None or not np.all(np.isfinite(values)):
        for (line_no, _), toks in zip(rest, split):
            for k, t in enumerate(toks):
                try:
                    ok = math.isfinite(float(t))
                except ValueError:
                    ok = False
                if not ok:
                    raise InputFileError(source, f"line {line_no}: value {k + 1} is not a finite number: {t[:20]!r}")
    return BvhMotion(
        names=tuple(out["names"]),
        parents=np.array(out["parents"], dtype=np.int64),
        offsets=np.array(out["offsets"], dtype=np.float64).reshape(-1, 3),
        channels=tuple(out["channels"]),
        end_site_parents=np.array(out["end_parents"], dtype=np.int64),
        end_site_offsets=np.array(out["end_offsets"], dtype=np.float64).reshape(-1, 3),
        frame_time=frame_time,
        values=values.reshape(n_frames, n_chan),
        source=source,
    )


def read_bvh(path) -> BvhMotion:
    """Reads a BVH file. Errors: InputFileError(path, "line N: ...")."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputFileError(path, f"cannot read: {e.strerror or e}") from None
    return parse_bvh(FieldChecks(path).decode(data), str(path))


# ---------------------------------------------------------------------------------------------
# Writing


def format_bvh(motion: BvhMotion) -> str:
    """The BVH text of `motion` (tabs for indentation, values with VALUE_FORMAT)."""
    kids: dict[int, list[int]] = {j: [] for j in range(motion.num_joints)}
    for j, p in enumerate(motion.parents):
        if p >= 0:
            kids[int(p)].append(j)
    sites: dict[int, list[int]] = {j: [] for j in range(motion.num_joints)}
    for e, p in enumerate(motion.end_site_parents):
        sites[int(p)].append(e)
    fmt3 = " ".join([VALUE_FORMAT] * 3)
    out = ["HIERARCHY"]

    def joint(j: int, depth: int):
        ind = "\t" * depth
        out.append(f"{ind}{'ROOT' if motion.parents[j] < 0 else 'JOINT'} {motion.names[j]}")
        out.append(f"{ind}{{")
        out.append(f"{ind}\tOFFSET " + fmt3 % tuple(motion.offsets[j]))
        if motion.channels[j]:
            out.append(f"{ind}\tCHANNELS {len(motion.channels[j])} " + " ".join(motion.channels[j]))
        for k in kids[j]:
            joint(k, depth + 1)
        for e in sites[j]:
            out.append(f"{ind}\tEnd Site")
            out.append(f"{ind}\t{{")
            out.append(f"{ind}\t\tOFFSET " + fmt3 % tuple(motion.end_site_offsets[e]))
            out.append(f"{ind}\t}}")
        out.append(f"{ind}}}")

    for j in np.flatnonzero(motion.parents < 0):
        joint(int(j), 0)
    out.append("MOTION")
    out.append(f"Frames: {motion.num_frames}")
    out.append(f"Frame Time: {motion.frame_time!r}")
    row = " ".join([VALUE_FORMAT] * motion.num_channels)
    out.extend(row % tuple(v) for v in motion.values.tolist())
    return "\n".join(out) + "\n"


def write_bvh(path, motion: BvhMotion) -> None:
    """Writes `motion` to `path`; read_bvh gives it back to 1e-6 file units."""
    Path(path).write_text(format_bvh(motion), encoding="utf-8")


# ---------------------------------------------------------------------------------------------
# Forward kinematics


def _axis_rotations(axis: int, degrees: np.ndarray) -> np.ndarray:
    """(F,) degrees about axis 0/1/2 -> (F, 3, 3) rotation matrices."""
    a = np.deg2rad(degrees)
    c, s = np.cos(a), np.sin(a)
    m = np.zeros(a.shape + (3, 3))
    i, k = [(1, 2), (2, 0), (0, 1)][axis]
    m[..., axis, axis] = 1.0
    m[..., i, i] = c
    m[..., k, k] = c
    m[..., i, k] = -s
    m[..., k, i] = s
    return m


def _frame_values(motion: BvhMotion, frames) -> np.ndarray:
    if frames is None:
        return motion.values
    if isinstance(frames, (int, np.integer)):
        frames = [frames]
    return motion.values[frames]


def local_transforms(motion: BvhMotion, frames=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint local translations (F, J, 3) and rotations (F, J, 3, 3) in file units.

    frames: None (all), an int, a slice, or (K,) int indices.
    """
    vals = _frame_values(motion, frames)
    n = vals.shape[0]
    trans = np.broadcast_to(motion.offsets, (n,) + motion.offsets.shape).copy()
    rots = np.broadcast_to(np.eye(3), (n, motion.num_joints, 3, 3)).copy()
    for j, (start, chans) in enumerate(zip(motion.channel_starts, motion.channels)):
        r = None
        for k, c in enumerate(chans):
            col = vals[:, start + k]
            axis = "XYZ".index(c[0])
            if c in POSITION_CHANNELS:
                trans[:, j, axis] = col
            else:
                m = _axis_rotations(axis, col)
                r = m if r is None else r @ m
        if r is not None:
            rots[:, j] = r
    return trans, rots


def bvh_global_transforms(motion: BvhMotion, frames=None) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics: global joint positions (F, J, 3) and rotations (F, J, 3, 3).

    In the file's units and axes. frames: None (all), an int, a slice, or (K,) int indices.
    """
    trans, rots = local_transforms(motion, frames)
    pos = np.empty_like(trans)
    glob = np.empty_like(rots)
    for j, p in enumerate(motion.parents):
        if p < 0:
            pos[:, j] = trans[:, j]
            glob[:, j] = rots[:, j]
        else:
            pos[:, j] = pos[:, p] + np.einsum("fab,fb->fa", glob[:, p], trans[:, j])
            glob[:, j] = glob[:, p] @ rots[:, j]
    return pos, glob


def end_site_positions(motion: BvhMotion, frames=None, transforms=None) -> np.ndarray:
    """Global End Site positions (F, E, 3) in file units.

    transforms: the (positions, rotations) of bvh_global_transforms for the same frames, to
    avoid computing them twice.
    """
    pos, rot = transforms if transforms is not None else bvh_global_transforms(motion, frames)
    par = motion.end_site_parents
    return pos[:, par] + np.einsum("feab,eb->fea", rot[:, par], motion.end_site_offsets)


def rest_positions(motion: BvhMotion) -> tuple[np.ndarray, np.ndarray]:
    """The HIERARCHY pose (every OFFSET, no rotation): joints (J, 3) and End Sites (E, 3).

    This is the pose the OFFSETs describe, independent of the channel values.
    """
    pos = np.zeros((motion.num_joints, 3))
    for j, p in enumerate(motion.parents):
        pos[j] = motion.offsets[j] + (pos[p] if p >= 0 else 0.0)
    ends = pos[motion.end_site_parents] + motion.end_site_offsets
    return pos, ends
