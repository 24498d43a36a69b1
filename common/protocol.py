"""The cluster's wire codec: messages <-> lists of ZeroMQ frames. Pure functions, no sockets.

Every message is one msgpack header frame, plus raw binary frames for bulk data (only the
packed silhouettes of a ``Frame`` message)::

    [msgpack {"v": PROTOCOL_VERSION, "type": "solve", "session": str, "frame": int,
              "iteration": int, "request": int, ...fields of the type},  raw frames...]

The four routing keys are in every header; a type that does not use one sends "" or 0 there
(and decode insists on it). Use ``socket.send_multipart(encode(msg))`` and
``decode(frames)`` with the frames after any ROUTER identity frame. Set the socket's
``zmq.MAXMSGSIZE`` to ``MAX_MESSAGE_BYTES`` on a client and to ``MAX_CLIENT_MESSAGE_BYTES``
on the server, which receives only what clients send (zmq applies it to each frame; decode
checks the sum, and refuses more than ``MAX_PARTS`` frames). See docs/cluster.md for why
zmq holds a whole message before any of it is delivered, and CURVE is the defence.

Everything from the wire is hostile until ``decode`` returns: it raises ``ProtocolError``
with a short ``reason`` from ``REASONS`` (so servers can count drops by reason) and never
unpickles or asserts. The message dataclasses validate their fields when built, so a
message that would be refused is refused at the sender too, with the same error.

One module of about 550 lines: one wire codec, every message type with its validation, as
DESIGN.md asks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from numbers import Integral, Real
from typing import ClassVar

import msgpack
import numpy as np

from common.camera import Camera, CalibrationError, Studio, make_camera
from common.packing import clear_padding, packed_length, padded_shape, unpackbits_masks

PROTOCOL_VERSION = 8  # 2: hops (HOP_JOB_NAMES) beside the chains; 3: cameras of different sizes; 4: whole fits;
#                       5: FRAME's body_scale (the actor's size); 6: windows count nothing past the image
#                       edges a silhouette touches (an older client's limb energies differ); 7: cameras
#                       weighted by the scale they see the body at (energy.camera_weights); 8: evolutions
#                       (EVOLVE_JOB_NAMES)
PARAM_COUNT = 35  # pose parameters of the body model
CHAIN_NAMES = ("torso", "head", "left_arm", "right_arm", "left_leg", "right_leg")
# the hops of a refinement's round (common.fitting.HOP_JOBS): sent and answered as chains are;
# job k of a Solve with iteration i is hop number i + k
HOP_JOB_NAMES = ("hop0", "hop1", "hop2", "hop3")
# a frame's evolutions (common.fitting.EVOLVE_JOBS): job k of a Solve with iteration i is
# evolution number i + k
EVOLVE_JOB_NAMES = ("evolve0", "evolve1", "evolve2", "evolve3")
# whole fits of a round of starts (common.search.FIT_JOBS), each Solve with its own start
FIT_JOB_NAMES = tuple(f"fit{k}" for k in range(16))
JOB_NAMES = CHAIN_NAMES + HOP_JOB_NAMES + EVOLVE_JOB_NAMES + FIT_JOB_NAMES

MAX_MESSAGE_BYTES = 64 * 1024 * 1024  # all frames of one message; also a client's zmq.MAXMSGSIZE
# The largest message a client sends is an Error of MAX_TEXT_CHARS 4-byte characters, 16.7 KB
# (tests/test_cluster_trust.py): the server's zmq.MAXMSGSIZE, 4x that, so a peer's frame of
# more closes its connection before zmq buffers it.
MAX_CLIENT_MESSAGE_BYTES = 64 * 1024
MAX_HEADER_BYTES = 1024 * 1024  # the msgpack header frame
MAX_CAMERAS = 64  # K
MAX_IMAGE_SIDE = 4096  # pixels, H and W
MAX_INDEX = 2**63 - 1  # frame, iteration, request, evaluation counts
MAX_CORES = 4096
MAX_HEARTBEAT_INTERVAL = 3600.0  # seconds
MAX_NAME_CHARS = 128  # session and client ids, camera, backend and option names, error codes
MAX_TEXT_CHARS = 4096  # error text, shutdown reason, string option values
MAX_BACKENDS = 16
MAX_OPTIONS = 64
BODY_SCALE_RANGE = (0.1, 10.0)  # FRAME's body_scale: far beyond any actor, short of a degenerate body
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1  # integer option values

# msgpack parse limits: far above any valid header, far below what would hurt.
_UNPACK_LIMITS = dict(max_str_len=4 * MAX_TEXT_CHARS, max_bin_len=0, max_ext_len=0,
                      max_array_len=1024, max_map_len=MAX_OPTIONS + 16)

REASONS = (
    "not_msgpack",   # the header frame is not a msgpack map
    "version",       # "v" missing or not PROTOCOL_VERSION
    "unknown_type",  # "type" missing, not a string, or not a known message type
    "bad_field",     # a field missing, unknown, of the wrong type or out of range
    "frame_count",   # wrong number of frames for the type
    "byte_length",   # packed silhouettes not ceil(K * H * W / 8) bytes
    "non_finite",    # NaN or infinity in a float field
    "too_large",     # message, header, frame count, K, H or W over its limit
)


class ProtocolError(ValueError):
    """A message that cannot be sent or was refused on receipt; ``reason`` is one of REASONS."""

    def __init__(self, reason: str, text: str):
        self.reason = reason
        self.text = text
        super().__init__(f"{reason}: {text}")


# ---------------------------------------------------------------------------- field checks

def _int(value, name: str, lo: int, hi: int, over: str = "bad_field") -> int:
    """``over`` is the reason for a value above ``hi`` (too_large for sizes)."""
    if isinstance(value, bool) or not isinstance(value, Integral):
        raise ProtocolError("bad_field", f"{name}: expected an integer, got {type(value).__name__}")
    if not lo <= value <= hi:
        raise ProtocolError(over if value > hi else "bad_field", f"{name}: {value} not in [{lo}, {hi}]")
    return int(value)


def _float(value, name: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, Real):
        raise ProtocolError("bad_field", f"{name}: expected a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise ProtocolError("non_finite", f"{name}: {value}")
    if not lo <= value <= hi:
        raise ProtocolError("bad_field", f"{name}: {value} not in [{lo}, {hi}]")
    return value


def _str(value, name: str, max_chars: int, allow_empty: bool = True) -> str:
    if not isinstance(value, str):
        raise ProtocolError("bad_field", f"{name}: expected a string, got {type(value).__name__}")
    if len(value) > max_chars or (not value and not allow_empty):
        raise ProtocolError("bad_field", f"{name}: length {len(value)} not in "
                                         f"[{0 if allow_empty else 1}, {max_chars}]")
    return value


def _sequence(value, name: str) -> tuple:
    if not isinstance(value, (list, tuple, np.ndarray)):
        raise ProtocolError("bad_field", f"{name}: expected a list, got {type(value).__name__}")
    return tuple(value)


def _floats(value, name: str, count: int) -> tuple[float, ...]:
    items = _sequence(value, name)
    if len(items) != count:
        raise ProtocolError("bad_field", f"{name}: expected {count} numbers, got {len(items)}")
    return tuple(_float(v, f"{name}[{i}]") for i, v in enumerate(items))


def _matrix(value, name: str, rows: int, cols: int) -> tuple[tuple[float, ...], ...]:
    items = _sequence(value, name)
    if len(items) != rows:
        raise ProtocolError("bad_field", f"{name}: expected {rows} rows, got {len(items)}")
    return tuple(_floats(row, f"{name}[{i}]", cols) for i, row in enumerate(items))


def _names(value, name: str, allowed: tuple[str, ...] | None, max_count: int) -> tuple[str, ...]:
    items = _sequence(value, name)
    if not 1 <= len(items) <= max_count:
        raise ProtocolError("bad_field", f"{name}: expected 1..{max_count} names, got {len(items)}")
    names = tuple(_str(v, f"{name}[{i}]", MAX_NAME_CHARS, allow_empty=False) for i, v in enumerate(items))
    if len(set(names)) != len(names):
        raise ProtocolError("bad_field", f"{name}: duplicate names in {list(names)}")
    if allowed is not None:
        for n in names:
            if n not in allowed:
                raise ProtocolError("bad_field", f"{name}: {n!r} is not one of {list(allowed)}")
    return names


def _job(value, name: str) -> str:
    if not isinstance(value, str) or value not in JOB_NAMES:
        raise ProtocolError("bad_field", f"{name}: {value!r} is not one of {list(JOB_NAMES)}")
    return value


def _option(value, name: str):
    if isinstance(value, bool):
        return value
    if isinstance(value, Integral):
        return _int(value, name, INT64_MIN, INT64_MAX)
    if isinstance(value, Real):
        return _float(value, name)
    if isinstance(value, str):
        return _str(value, name, MAX_TEXT_CHARS)
    raise ProtocolError("bad_field", f"{name}: expected a bool, int, float or string, "
                                     f"got {type(value).__name__}")


def _set(obj, name: str, value) -> None:
    object.__setattr__(obj, name, value)  # normalising fields of a frozen dataclass


def _session(obj, required: bool) -> None:
    _set(obj, "session", _str(obj.session, f"{obj.TYPE}.session", MAX_NAME_CHARS, allow_empty=not required))


def _indices(obj, *names: str) -> None:
    for n in names:
        _set(obj, n, _int(getattr(obj, n), f"{obj.TYPE}.{n}", 0, MAX_INDEX))


# ---------------------------------------------------------------------------- messages

@dataclass(frozen=True, kw_only=True)
class CameraSpec:
    """One camera of a studio as it travels: plain numbers, checked like a calibration file.

    K: 3x3 intrinsics in pixels; dist: k1 k2 p1 p2 k3; R: 3x3 world-to-camera rotation;
    t: 3 world-to-camera translation in metres; width, height in pixels.
    """

    name: str
    K: tuple[tuple[float, ...], ...]
    dist: tuple[float, ...]
    R: tuple[tuple[float, ...], ...]
    t: tuple[float, ...]
    width: int
    height: int

    def __post_init__(self):
        _set(self, "name", _str(self.name, "camera.name", MAX_NAME_CHARS, allow_empty=False))
        prefix = f"camera {self.name!r}"
        _set(self, "K", _matrix(self.K, f"{prefix}.K", 3, 3))
        _set(self, "dist", _floats(self.dist, f"{prefix}.dist", 5))
        _set(self, "R", _matrix(self.R, f"{prefix}.R", 3, 3))
        _set(self, "t", _floats(self.t, f"{prefix}.t", 3))
        for n in ("width", "height"):
            _set(self, n, _int(getattr(self, n), f"{prefix}.{n}", 1, MAX_IMAGE_SIDE, over="too_large"))
        try:
            self.to_camera()
        except CalibrationError as exc:
            raise ProtocolError("bad_field", str(exc)) from None

    @classmethod
    def from_camera(cls, camera: Camera) -> "CameraSpec":
        return cls(name=camera.name, K=camera.K.tolist(), dist=camera.dist.tolist(), R=camera.R.tolist(),
                   t=camera.t.tolist(), width=camera.width, height=camera.height)

    def to_camera(self) -> Camera:
        return make_camera(self.name, self.K, self.dist, self.R, self.t, self.width, self.height, "<wire>")


@dataclass(frozen=True, kw_only=True)
class Register:
    """Client -> server on connect and after every reconnect: who it is and what it can do."""

    TYPE: ClassVar[str] = "register"
    client_id: str
    cores: int
    backends: tuple[str, ...]  # energy backends it can run, e.g. ("cpu", "gl")
    version: str  # client software version (the protocol version is in every header)

    def __post_init__(self):
        _set(self, "client_id", _str(self.client_id, "register.client_id", MAX_NAME_CHARS, allow_empty=False))
        _set(self, "cores", _int(self.cores, "register.cores", 1, MAX_CORES))
        _set(self, "backends", _names(self.backends, "register.backends", None, MAX_BACKENDS))
        _set(self, "version", _str(self.version, "register.version", MAX_NAME_CHARS))


@dataclass(frozen=True, kw_only=True)
class Welcome:
    """Server -> client, answering Register: the session and the heartbeat interval to keep."""

    TYPE: ClassVar[str] = "welcome"
    session: str
    heartbeat_interval: float  # seconds

    def __post_init__(self):
        _session(self, required=True)
        _set(self, "heartbeat_interval", _float(self.heartbeat_interval, "welcome.heartbeat_interval",
                                                1e-3, MAX_HEARTBEAT_INTERVAL))


@dataclass(frozen=True, kw_only=True)
class Frame:
    """Server -> client, once per frame: the studio, the packed silhouettes, the start pose.

    Cameras may differ in image size: the silhouettes are the studio's padded (K, H, W) stack
    (``packing.pad_stack``; H, W the largest camera height and width, camera k's pixels at
    [:h_k, :w_k]), and ``silhouettes`` is its ``packing.packbits_masks``, sent as a raw frame.
    Bits on the padding carry nothing: ``masks`` clears them.
    """

    TYPE: ClassVar[str] = "frame"
    session: str
    frame: int
    cameras: tuple[CameraSpec, ...]
    silhouettes: bytes
    previous_params: tuple[float, ...]  # (PARAM_COUNT,) the previous frame's pose
    body_scale: float                   # the actor's size over the body model's (BodyModel.scale)
    body_fingerprint: str               # BodyModel.fingerprint of the body the server fits, at that size

    def __post_init__(self):
        _session(self, required=True)
        _indices(self, "frame")
        _set(self, "body_scale", _float(self.body_scale, "frame.body_scale", *BODY_SCALE_RANGE))
        _set(self, "body_fingerprint", _str(self.body_fingerprint, "frame.body_fingerprint", MAX_NAME_CHARS,
                                            allow_empty=False))
        cams = _sequence(self.cameras, "frame.cameras")
        if not cams:
            raise ProtocolError("bad_field", "frame.cameras: no cameras")
        if len(cams) > MAX_CAMERAS:
            raise ProtocolError("too_large", f"frame.cameras: {len(cams)} cameras, at most {MAX_CAMERAS}")
        for i, c in enumerate(cams):
            if not isinstance(c, CameraSpec):
                raise ProtocolError("bad_field", f"frame.cameras[{i}]: expected a CameraSpec")
        if len({c.name for c in cams}) != len(cams):
            raise ProtocolError("bad_field", "frame.cameras: duplicate camera names")
        _set(self, "cameras", cams)
        if not isinstance(self.silhouettes, (bytes, bytearray, memoryview)):
            raise ProtocolError("bad_field", "frame.silhouettes: expected bytes")
        _set(self, "silhouettes", bytes(self.silhouettes))
        expected = packed_length(self.K, self.H, self.W)
        if len(self.silhouettes) != expected:
            raise ProtocolError("byte_length", f"frame.silhouettes: {self.K}x{self.H}x{self.W} masks pack "
                                               f"to {expected} bytes, got {len(self.silhouettes)}")
        _set(self, "previous_params", _floats(self.previous_params, "frame.previous_params", PARAM_COUNT))

    @property
    def K(self) -> int:
        return len(self.cameras)

    @property
    def sizes(self) -> tuple[tuple[int, int], ...]:
        """(K, 2) (width, height) of each camera's image, pixels."""
        return tuple((c.width, c.height) for c in self.cameras)

    @property
    def H(self) -> int:
        return padded_shape(self.sizes)[0]

    @property
    def W(self) -> int:
        return padded_shape(self.sizes)[1]

    def masks(self) -> np.ndarray:
        """(K, H, W) bool silhouettes, the padded stack (False beyond each camera's image)."""
        return clear_padding(unpackbits_masks(self.silhouettes, self.K, self.H, self.W), self.sizes)

    def studio(self) -> Studio:
        return Studio(tuple(c.to_camera() for c in self.cameras), "<wire>")


@dataclass(frozen=True, kw_only=True)
class Solve:
    """Server -> client, per iteration: fit ``chains`` starting from the full pose ``params``
    (chains of CHAIN_NAMES, hops of HOP_JOB_NAMES: job k is hop number ``iteration`` + k,
    evolutions of EVOLVE_JOB_NAMES, numbered the same way, or a whole fit from ``params``,
    FIT_JOB_NAMES).

    ``options`` holds plain scalars (bool, int, float, str) such as grid steps or the energy
    backend; the solver refuses names it does not know.
    """

    TYPE: ClassVar[str] = "solve"
    session: str
    frame: int
    iteration: int
    request: int
    params: tuple[float, ...]  # (PARAM_COUNT,)
    chains: tuple[str, ...]
    options: dict = field(default_factory=dict)

    def __post_init__(self):
        _session(self, required=True)
        _indices(self, "frame", "iteration", "request")
        _set(self, "params", _floats(self.params, "solve.params", PARAM_COUNT))
        _set(self, "chains", _names(self.chains, "solve.chains", JOB_NAMES, len(JOB_NAMES)))
        if not isinstance(self.options, dict):
            raise ProtocolError("bad_field", f"solve.options: expected a map, got {type(self.options).__name__}")
        if len(self.options) > MAX_OPTIONS:
            raise ProtocolError("bad_field", f"solve.options: {len(self.options)} entries, at most {MAX_OPTIONS}")
        _set(self, "options", {_str(k, "solve.options key", MAX_NAME_CHARS, allow_empty=False):
                               _option(v, f"solve.options[{k!r}]") for k, v in self.options.items()})


@dataclass(frozen=True, kw_only=True)
class Result:
    """Client -> server: the fitted pose of one chain (or hop) of a Solve request, and its cost."""

    TYPE: ClassVar[str] = "result"
    session: str
    frame: int
    iteration: int
    request: int
    chain: str
    params: tuple[float, ...]  # (PARAM_COUNT,) the full pose with this chain fitted
    energy: float
    energy_before: float
    evaluations: int
    iterations: int
    cpu_seconds: float
    wall_seconds: float

    def __post_init__(self):
        _session(self, required=True)
        _indices(self, "frame", "iteration", "request", "evaluations", "iterations")
        _set(self, "energy_before", _float(self.energy_before, "result.energy_before"))
        _set(self, "chain", _job(self.chain, "result.chain"))
        _set(self, "params", _floats(self.params, "result.params", PARAM_COUNT))
        _set(self, "energy", _float(self.energy, "result.energy"))
        for n in ("cpu_seconds", "wall_seconds"):
            _set(self, n, _float(getattr(self, n), f"result.{n}", 0.0))


@dataclass(frozen=True, kw_only=True)
class Heartbeat:
    """Both ways while idle; ``session`` lets a client notice a restarted server."""

    TYPE: ClassVar[str] = "heartbeat"
    session: str = ""

    def __post_init__(self):
        _session(self, required=False)


@dataclass(frozen=True, kw_only=True)
class Error:
    """Either way: a request that could not be served. The routing keys name it, when there is one."""

    TYPE: ClassVar[str] = "error"
    code: str
    text: str
    session: str = ""
    frame: int = 0
    iteration: int = 0
    request: int = 0

    def __post_init__(self):
        _set(self, "code", _str(self.code, "error.code", MAX_NAME_CHARS, allow_empty=False))
        _set(self, "text", _str(self.text, "error.text", MAX_TEXT_CHARS))
        _session(self, required=False)
        _indices(self, "frame", "iteration", "request")


@dataclass(frozen=True, kw_only=True)
class Shutdown:
    """Server -> client: stop working and exit."""

    TYPE: ClassVar[str] = "shutdown"
    reason: str
    session: str = ""

    def __post_init__(self):
        _set(self, "reason", _str(self.reason, "shutdown.reason", MAX_TEXT_CHARS))
        _session(self, required=False)


Message = Register | Welcome | Frame | Solve | Result | Heartbeat | Error | Shutdown
MESSAGE_TYPES = {cls.TYPE: cls for cls in (Register, Welcome, Frame, Solve, Result, Heartbeat, Error, Shutdown)}


def camera_specs(studio: Studio) -> tuple[CameraSpec, ...]:
    """The cameras of ``studio``, in order (the bit order of its silhouettes), for a Frame."""
    return tuple(CameraSpec.from_camera(c) for c in studio)


_ROUTING = {"session": "", "frame": 0, "iteration": 0, "request": 0}  # value sent when unused
_RAW_FIELDS = {Frame: ("silhouettes",)}  # fields sent as raw frames after the header, in order
MAX_PARTS = 1 + max(len(names) for names in _RAW_FIELDS.values())  # frames of the longest message
_CAMERA_KEYS = tuple(f.name for f in fields(CameraSpec))


# ---------------------------------------------------------------------------- codec

def encode(msg: Message) -> list[bytes]:
    """Message -> [msgpack header, raw frames...], ready for ``send_multipart``."""
    cls = type(msg)
    if MESSAGE_TYPES.get(getattr(cls, "TYPE", None)) is not cls:
        raise TypeError(f"not a protocol message: {cls.__name__}")
    raw_names = _RAW_FIELDS.get(cls, ())
    header = {"v": PROTOCOL_VERSION, "type": cls.TYPE}
    header.update({k: getattr(msg, k, neutral) for k, neutral in _ROUTING.items()})
    for f in fields(msg):
        if f.name not in header and f.name not in raw_names:
            header[f.name] = getattr(msg, f.name)
    if cls is Frame:
        header.update(K=msg.K, H=msg.H, W=msg.W,
                      cameras=[{k: getattr(c, k) for k in _CAMERA_KEYS} for c in msg.cameras])
    parts = [msgpack.packb(header, use_bin_type=True)] + [getattr(msg, n) for n in raw_names]
    if len(parts[0]) > MAX_HEADER_BYTES:
        raise ProtocolError("too_large", f"{cls.TYPE} header is {len(parts[0])} bytes, at most {MAX_HEADER_BYTES}")
    total = sum(len(p) for p in parts)
    if total > MAX_MESSAGE_BYTES:
        raise ProtocolError("too_large", f"{cls.TYPE} message is {total} bytes, at most {MAX_MESSAGE_BYTES}")
    return parts


def decode(frames: list[bytes]) -> Message:
    """[msgpack header, raw frames...] from ``recv_multipart`` -> a validated message.

    Raises ProtocolError(reason, text) for anything but a well-formed message of this
    protocol version; see REASONS.
    """
    if not frames:
        raise ProtocolError("frame_count", "no frames")
    if len(frames) > MAX_PARTS:
        raise ProtocolError("too_large", f"{len(frames)} frames, at most {MAX_PARTS}")
    parts = [memoryview(f) for f in frames]
    total = sum(p.nbytes for p in parts)
    if total > MAX_MESSAGE_BYTES:
        raise ProtocolError("too_large", f"message is {total} bytes, at most {MAX_MESSAGE_BYTES}")
    if parts[0].nbytes > MAX_HEADER_BYTES:
        raise ProtocolError("too_large", f"header is {parts[0].nbytes} bytes, at most {MAX_HEADER_BYTES}")
    try:
        header = msgpack.unpackb(parts[0], raw=False, strict_map_key=True, **_UNPACK_LIMITS)
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise ProtocolError("not_msgpack", f"header: {exc}") from None
    if not isinstance(header, dict):
        raise ProtocolError("not_msgpack", f"header is a {type(header).__name__}, not a map")

    version = header.pop("v", None)
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise ProtocolError("version", f"protocol version {version!r}, expected {PROTOCOL_VERSION}")
    type_name = header.pop("type", None)
    cls = MESSAGE_TYPES.get(type_name) if isinstance(type_name, str) else None
    if cls is None:
        raise ProtocolError("unknown_type", f"message type {type_name!r}")
    raw_names = _RAW_FIELDS.get(cls, ())
    if len(parts) != 1 + len(raw_names):
        raise ProtocolError("frame_count", f"{type_name}: {len(parts)} frames, expected {1 + len(raw_names)}")

    names = {f.name for f in fields(cls)}
    expected = (names | set(_ROUTING)) - set(raw_names)
    if cls is Frame:
        expected |= {"K", "H", "W"}
    _check_keys(header, expected, type_name)
    for key, neutral in _ROUTING.items():
        if key not in names and (type(header[key]) is not type(neutral) or header[key] != neutral):
            raise ProtocolError("bad_field", f"{type_name}.{key}: unused here, must be {neutral!r}")
        if key not in names:
            del header[key]
    if cls is Frame:
        return _decode_frame(header, bytes(parts[1]))
    return cls(**header)


def _check_keys(mapping: dict, expected: set, what: str) -> None:
    missing = expected - mapping.keys()
    if missing:
        raise ProtocolError("bad_field", f"{what}: missing {sorted(missing)}")
    unknown = mapping.keys() - expected
    if unknown:
        raise ProtocolError("bad_field", f"{what}: unknown {sorted(unknown)}")


def _decode_frame(header: dict, silhouettes: bytes) -> Frame:
    # Sizes and byte length first: cheap, and they bound the work the rest costs.
    K = _int(header.pop("K"), "frame.K", 1, MAX_CAMERAS, over="too_large")
    H = _int(header.pop("H"), "frame.H", 1, MAX_IMAGE_SIDE, over="too_large")
    W = _int(header.pop("W"), "frame.W", 1, MAX_IMAGE_SIDE, over="too_large")
    if len(silhouettes) != packed_length(K, H, W):
        raise ProtocolError("byte_length", f"frame.silhouettes: {K}x{H}x{W} masks pack to "
                                           f"{packed_length(K, H, W)} bytes, got {len(silhouettes)}")
    cameras = header.pop("cameras")
    if not isinstance(cameras, list) or len(cameras) != K:
        raise ProtocolError("bad_field", f"frame.cameras: expected a list of K = {K} cameras")
    specs = []
    for i, c in enumerate(cameras):
        if not isinstance(c, dict):
            raise ProtocolError("bad_field", f"frame.cameras[{i}]: expected a map")
        _check_keys(c, set(_CAMERA_KEYS), f"frame.cameras[{i}]")
        specs.append(CameraSpec(**c))
    largest = padded_shape([(c.width, c.height) for c in specs])
    if largest != (H, W):
        raise ProtocolError("bad_field", f"frame: H x W = {H}x{W} but the cameras' largest height "
                                         f"and width are {largest[0]}x{largest[1]}")
    return Frame(cameras=tuple(specs), silhouettes=silhouettes, **header)
