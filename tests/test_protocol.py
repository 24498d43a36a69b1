"""The wire codec, without sockets: round trips of every type and every way decode refuses."""
import math

import msgpack
import numpy as np
import pytest

from common import protocol
from common.camera import circle_studio
from common.packing import packbits_masks, packed_length
from common.protocol import (CHAIN_NAMES, JOB_NAMES, MAX_CAMERAS, MAX_HEADER_BYTES, MAX_IMAGE_SIDE, MAX_INDEX,
                             MAX_MESSAGE_BYTES, MAX_PARTS, PARAM_COUNT, PROTOCOL_VERSION, REASONS, CameraSpec, Error,
                             Frame, Heartbeat, ProtocolError, Register, Result, Shutdown, Solve, Welcome,
                             camera_specs, decode, encode)

try:
    from hypothesis import given, settings, strategies as st
except ImportError:  # not in every environment yet; the fixed examples below still run
    given = None

PARAMS = tuple(0.01 * i - 0.1 for i in range(PARAM_COUNT))


def test_the_wire_knows_the_fitters_chains_hops_and_evolutions():
    from common.body import CHAINS
    from common.fitting import EVOLVE_JOBS, HOP_JOBS
    from common.search import FIT_JOBS

    assert set(CHAIN_NAMES) == set(CHAINS) and protocol.HOP_JOB_NAMES == HOP_JOBS
    assert protocol.FIT_JOB_NAMES == FIT_JOBS and protocol.EVOLVE_JOB_NAMES == EVOLVE_JOBS
    assert JOB_NAMES == CHAIN_NAMES + HOP_JOBS + EVOLVE_JOBS + FIT_JOBS
    solve = Solve(session="s", frame=3, iteration=8, request=1, params=PARAMS, chains=HOP_JOBS[:2])
    assert decode(encode(solve)) == solve
    with pytest.raises(ProtocolError, match="'hop9' is not one of"):
        Solve(session="s", frame=3, iteration=8, request=1, params=PARAMS, chains=("hop9",))


def make_frame(K=5, H=17, W=33, seed=0, **overrides) -> Frame:
    masks = np.random.default_rng(seed).random((K, H, W)) < 0.3
    fields = dict(session="s1", frame=7, cameras=camera_specs(circle_studio(K, W, H)),
                  silhouettes=packbits_masks(masks), previous_params=PARAMS, body_scale=1.0,
                        body_fingerprint="0123456789abcdef")
    fields.update(overrides)
    return Frame(**fields)


EXAMPLES = [
    Register(client_id="worker-1", cores=2, backends=("cpu", "gl"), version="0.1.0"),
    Welcome(session="s1", heartbeat_interval=1.0),
    make_frame(),
    make_frame(K=9, H=1, W=1),
    Solve(session="s1", frame=7, iteration=2, request=41, params=PARAMS, chains=("left_arm", "right_leg"),
          options={"grid_steps": 5, "backend": "cpu", "step": 0.05, "prerender": True}),
    Solve(session="s1", frame=0, iteration=0, request=0, params=PARAMS, chains=("head",)),
    Result(session="s1", frame=7, iteration=2, request=41, chain="left_arm", params=PARAMS, energy=1234.0,
           energy_before=1500.0, evaluations=900, iterations=3, cpu_seconds=0.25, wall_seconds=0.3),
    Heartbeat(),
    Heartbeat(session="s1"),
    Error(code="busy", text="no free core"),
    Error(code="solve_failed", text="ü ✓", session="s1", frame=7, iteration=2, request=41),
    Shutdown(reason="sequence done", session="s1"),
]


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip(msg):
    frames = encode(msg)
    assert all(isinstance(f, bytes) for f in frames)
    assert len(frames) == (2 if isinstance(msg, Frame) else 1)
    assert decode(frames) == msg
    assert decode([memoryview(f) for f in frames]) == msg  # zmq.Frame-like buffers too


def test_every_type_has_an_example():
    assert {type(m) for m in EXAMPLES} == set(protocol.MESSAGE_TYPES.values())


def test_header_layout():
    msg = EXAMPLES[4]
    header = msgpack.unpackb(encode(msg)[0])
    assert header["v"] == PROTOCOL_VERSION and header["type"] == "solve"
    assert (header["session"], header["frame"], header["iteration"], header["request"]) == ("s1", 7, 2, 41)
    register = msgpack.unpackb(encode(EXAMPLES[0])[0])
    assert (register["session"], register["frame"], register["iteration"], register["request"]) == ("", 0, 0, 0)


def test_frame_payload_is_raw_packbits_and_masks_come_back():
    masks = np.random.default_rng(3).random((9, 11, 13)) < 0.5
    msg = make_frame(K=9, H=11, W=13, silhouettes=packbits_masks(masks))
    header, payload = encode(msg)
    assert payload == packbits_masks(masks)
    assert b"silhouettes" not in header
    out = decode([header, payload])
    assert (out.K, out.H, out.W) == (9, 11, 13)
    np.testing.assert_array_equal(out.masks(), masks)
    studio = out.studio()
    np.testing.assert_allclose(studio[0].K, circle_studio(9, 13, 11)[0].K)


def test_values_are_normalised():
    msg = Solve(session="s", frame=np.int64(3), iteration=0, request=1, params=np.zeros(PARAM_COUNT),
                chains=["torso"], options={"steps": np.int32(4), "scale": np.float64(0.5)})
    assert msg.params == (0.0,) * PARAM_COUNT and type(msg.frame) is int
    assert type(msg.options["steps"]) is int and type(msg.options["scale"]) is float
    assert decode(encode(msg)) == msg
    result = Result(session="s", frame=0, iteration=0, request=0, chain="head", params=PARAMS, energy=3,
                    energy_before=4, evaluations=1, iterations=1, cpu_seconds=0, wall_seconds=0)
    assert type(result.energy) is float


# ---------------------------------------------------------------------------- rejections

def rejects(frames, reason):
    with pytest.raises(ProtocolError) as info:
        decode(frames)
    assert info.value.reason == reason, str(info.value)
    assert reason in REASONS
    return info.value


def tampered(msg, drop=(), **changes):
    """encode(msg) with its header edited: keys in ``drop`` removed, ``changes`` set."""
    frames = encode(msg)
    header = msgpack.unpackb(frames[0])
    for k in drop:
        del header[k]
    header.update(changes)
    return [msgpack.packb(header)] + frames[1:]


SOLVE, RESULT, FRAME, REGISTER = EXAMPLES[4], EXAMPLES[6], EXAMPLES[2], EXAMPLES[0]


@pytest.mark.parametrize("header", [
    b"", b"\xc1", b"\x92\x01", b"\x81\xa1v\x01extra", b"not msgpack at all",
    msgpack.packb([1, 2]), msgpack.packb("solve"), msgpack.packb(None),
    msgpack.packb({1: "int key"}),
    msgpack.packb({"v": PROTOCOL_VERSION, "type": "heartbeat", "blob": b"bytes in the header"}),
    msgpack.packb({"v": PROTOCOL_VERSION, "type": "heartbeat", "t": msgpack.ExtType(5, b"x")}),
    b"\x81\xa1v\xa2\xff\xfe",  # invalid UTF-8 string
    msgpack.packb({"text": "x" * (4 * protocol.MAX_TEXT_CHARS + 1)}),
    msgpack.packb({"a": list(range(5000))}),
    b"\x91" * 200000 + b"\x01",  # nesting deeper than the unpacker allows
], ids=range(15))
def test_not_msgpack(header):
    rejects([header], "not_msgpack")


@pytest.mark.parametrize("version", [None, 0, PROTOCOL_VERSION - 1, PROTOCOL_VERSION + 1, str(PROTOCOL_VERSION),
                                     float(PROTOCOL_VERSION), True, [PROTOCOL_VERSION]])
def test_version(version):
    frames = tampered(SOLVE, drop=["v"]) if version is None else tampered(SOLVE, v=version)
    rejects(frames, "version")


@pytest.mark.parametrize("type_name", [None, "nope", "Solve", 5, "", ["solve"]])
def test_unknown_type(type_name):
    frames = tampered(SOLVE, drop=["type"]) if type_name is None else tampered(SOLVE, type=type_name)
    rejects(frames, "unknown_type")


@pytest.mark.parametrize("msg, frames", [
    (SOLVE, lambda f: f + [b"extra"]),
    (FRAME, lambda f: f[:1]),
    (REGISTER, lambda f: f + [b""]),
])
def test_frame_count(msg, frames):
    rejects(frames(encode(msg)), "frame_count")


@pytest.mark.parametrize("msg, extra", [(FRAME, 1), (REGISTER, 2), (Heartbeat(), 1000)])
def test_more_frames_than_any_message_is_too_large(msg, extra):
    """Refused before the header is read: a flood, whatever its frames hold."""
    frames = encode(msg) + [b""] * extra
    assert len(frames) > MAX_PARTS
    rejects(frames, "too_large")


def test_no_frames():
    rejects([], "frame_count")


@pytest.mark.parametrize("msg, drop, changes", [
    (SOLVE, ["params"], {}),
    (SOLVE, ["session"], {}),
    (SOLVE, ["request"], {}),
    (RESULT, ["energy"], {}),
    (SOLVE, [], {"priority": 1}),
    (SOLVE, [], {"frame": "7"}),
    (SOLVE, [], {"frame": 7.0}),
    (SOLVE, [], {"frame": True}),
    (SOLVE, [], {"frame": -1}),
    (SOLVE, [], {"request": 2**64 - 1}),
    (SOLVE, [], {"iteration": None}),
    (SOLVE, [], {"session": ""}),
    (SOLVE, [], {"session": 5}),
    (SOLVE, [], {"session": "s" * 129}),
    (SOLVE, [], {"params": [0.0] * 34}),
    (SOLVE, [], {"params": [0.0] * 36}),
    (SOLVE, [], {"params": "0" * 35}),
    (SOLVE, [], {"params": [0.0] * 34 + ["x"]}),
    (SOLVE, [], {"params": [0.0] * 34 + [True]}),
    (SOLVE, [], {"params": [[0.0]] * 35}),
    (SOLVE, [], {"chains": []}),
    (SOLVE, [], {"chains": ["left_hand"]}),
    (SOLVE, [], {"chains": ["head", "head"]}),
    (SOLVE, [], {"chains": "head"}),
    (SOLVE, [], {"options": [1, 2]}),
    (SOLVE, [], {"options": {"grid": [1, 2]}}),
    (SOLVE, [], {"options": {"grid": {"a": 1}}}),
    (SOLVE, [], {"options": {"grid": None}}),
    (SOLVE, [], {"options": {"": 1}}),
    (SOLVE, [], {"options": {"big": 2**63}}),
    (RESULT, [], {"chain": "tail"}),
    (RESULT, [], {"chain": ["head"]}),
    (RESULT, [], {"evaluations": -1}),
    (RESULT, [], {"cpu_seconds": -0.5}),
    (RESULT, [], {"energy": "1.0"}),
    (REGISTER, [], {"cores": 0}),
    (REGISTER, [], {"cores": 10**6}),
    (REGISTER, [], {"backends": []}),
    (REGISTER, [], {"backends": ["cpu", 1]}),
    (REGISTER, [], {"client_id": ""}),
    (REGISTER, [], {"session": "s1"}),  # routing keys a type does not use stay neutral
    (REGISTER, [], {"frame": 3}),
    (REGISTER, [], {"request": False}),
    (EXAMPLES[1], [], {"heartbeat_interval": 0.0}),
    (EXAMPLES[1], [], {"heartbeat_interval": 1e9}),
    (EXAMPLES[9], [], {"code": ""}),
    (EXAMPLES[9], [], {"text": 5}),
    (FRAME, ["cameras"], {}),
    (FRAME, ["previous_params"], {}),
    (FRAME, ["body_fingerprint"], {}),
    (FRAME, ["body_scale"], {}),
    (FRAME, [], {"body_scale": 0.0}),
    (FRAME, [], {"body_scale": "1.4"}),
    (FRAME, [], {"body_fingerprint": ""}),
    (FRAME, [], {"body_fingerprint": 7}),
    (FRAME, [], {"previous_params": [0.0] * 3}),
    (FRAME, [], {"K": 4}),  # with a payload sized for K = 4: K must match the 5 cameras
    (FRAME, [], {"K": 0}),
    (FRAME, [], {"K": "5"}),
    (FRAME, [], {"cameras": "cams"}),
    (FRAME, [], {"cameras": [1, 2, 3, 4, 5]}),
], ids=range(61))
def test_bad_field(msg, drop, changes):
    frames = tampered(msg, drop, **changes)
    if msg is FRAME and changes.get("K") == 4:
        frames[1] = frames[1][:packed_length(4, 17, 33)]  # right length for K = 4
    rejects(frames, "bad_field")


def frame_header(**changes):
    header = msgpack.unpackb(encode(FRAME)[0])
    header.update(changes)
    return header


def camera_maps(**changes):
    cams = frame_header()["cameras"]
    for c in cams:
        c.update(changes)
    return cams


@pytest.mark.parametrize("cameras", [
    lambda: camera_maps(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]),  # not a rotation
    lambda: camera_maps(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]),  # a reflection
    lambda: camera_maps(K=[[0, 0, 0], [0, 1, 0], [0, 0, 1]]),
    lambda: camera_maps(K=[1, 2, 3]),
    lambda: camera_maps(dist=[0, 0, 0, 0]),
    lambda: camera_maps(t=[0, 0]),
    lambda: camera_maps(width=True),
    lambda: camera_maps(name=""),
    lambda: camera_maps(extra=1),
    lambda: [{k: v for k, v in c.items() if k != "R"} for c in camera_maps()],
    lambda: [dict(c, name="same") for c in camera_maps()],
    lambda: [dict(c, width=34) if i == 2 else c for i, c in enumerate(camera_maps())],  # sizes differ
    lambda: camera_maps(width=66, height=34),  # cameras 66x34, header says 33x17
])
def test_bad_camera(cameras):
    rejects([msgpack.packb(frame_header(cameras=cameras())), encode(FRAME)[1]], "bad_field")


@pytest.mark.parametrize("delta", [-1, 1, -packed_length(5, 17, 33)])
def test_byte_length(delta):
    header, payload = encode(FRAME)
    payload = payload[:delta] if delta < 0 else payload + b"\0" * delta
    rejects([header, payload], "byte_length")


def test_byte_length_follows_header_sizes():
    header, payload = encode(FRAME)
    rejects([msgpack.packb(frame_header(H=18)), payload], "byte_length")


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("msg, changes", [
    (SOLVE, {"params": [0.0] * 34 + [NAN]}),
    (SOLVE, {"params": [INF] + [0.0] * 34}),
    (SOLVE, {"options": {"step": NAN}}),
    (RESULT, {"params": [0.0] * 34 + [-INF]}),
    (RESULT, {"energy": NAN}),
    (RESULT, {"energy": INF}),
    (RESULT, {"cpu_seconds": NAN}),
    (RESULT, {"wall_seconds": INF}),
    (FRAME, {"previous_params": [NAN] * 35}),
    (FRAME, {"body_scale": NAN}),
    (FRAME, {"cameras": camera_maps(t=[0.0, NAN, 0.0])}),
    (EXAMPLES[1], {"heartbeat_interval": INF}),
])
def test_non_finite(msg, changes):
    rejects(tampered(msg, **changes), "non_finite")


@pytest.mark.parametrize("changes", [
    {"K": MAX_CAMERAS + 1}, {"H": MAX_IMAGE_SIDE + 1}, {"W": MAX_IMAGE_SIDE + 1}, {"W": 2**40},
])
def test_too_large_sizes(changes):
    rejects(tampered(FRAME, **changes), "too_large")


def test_too_large_camera_size():
    cams = camera_maps(width=MAX_IMAGE_SIDE + 1)
    rejects([msgpack.packb(frame_header(cameras=cams)), encode(FRAME)[1]], "too_large")


def test_too_large_message_and_header():
    header = encode(FRAME)[0]
    rejects([header, bytes(MAX_MESSAGE_BYTES)], "too_large")
    rejects([msgpack.packb({"v": PROTOCOL_VERSION, "pad": "x" * MAX_HEADER_BYTES})], "too_large")


def test_too_large_on_encode(monkeypatch):
    monkeypatch.setattr(protocol, "MAX_MESSAGE_BYTES", 100)
    with pytest.raises(ProtocolError) as info:
        encode(FRAME)
    assert info.value.reason == "too_large"
    monkeypatch.setattr(protocol, "MAX_HEADER_BYTES", 10)
    with pytest.raises(ProtocolError) as info:
        encode(SOLVE)
    assert info.value.reason == "too_large"


# ---------------------------------------------------------------------------- sender side

@pytest.mark.parametrize("build, reason", [
    (lambda: Solve(session="s", frame=0, iteration=0, request=0, params=PARAMS[:-1], chains=["head"]),
     "bad_field"),
    (lambda: Solve(session="s", frame=0, iteration=0, request=0, params=PARAMS, chains=["neck"]), "bad_field"),
    (lambda: Result(session="s", frame=0, iteration=0, request=0, chain="head", params=PARAMS,
                    energy=math.nan, energy_before=0.0, evaluations=0, iterations=0, cpu_seconds=0.0,
                    wall_seconds=0.0), "non_finite"),
    (lambda: make_frame(silhouettes=b"\0"), "byte_length"),
    (lambda: make_frame(silhouettes="text"), "bad_field"),
    (lambda: make_frame(cameras=()), "bad_field"),
    (lambda: make_frame(cameras=[{"name": "c"}]), "bad_field"),
    (lambda: make_frame(cameras=camera_specs(circle_studio(5, 33, 17)) * 13), "too_large"),
    (lambda: Welcome(session="", heartbeat_interval=1.0), "bad_field"),
])
def test_invalid_messages_cannot_be_built(build, reason):
    with pytest.raises(ProtocolError) as info:
        build()
    assert info.value.reason == reason


def test_encode_refuses_non_messages():
    with pytest.raises(TypeError):
        encode({"type": "solve"})
    with pytest.raises(TypeError):
        encode(CameraSpec.from_camera(circle_studio(1)[0]))


def test_error_names_reason_and_field():
    err = rejects(tampered(SOLVE, chains=["tail"]), "bad_field")
    assert err.text in str(err) and "solve.chains" in str(err) and str(err).startswith("bad_field: ")


# ---------------------------------------------------------------------------- properties

if given is not None:
    finite = st.floats(allow_nan=False, allow_infinity=False)
    params = st.lists(finite, min_size=PARAM_COUNT, max_size=PARAM_COUNT)
    index = st.integers(0, MAX_INDEX)
    name = st.text(min_size=1, max_size=protocol.MAX_NAME_CHARS)
    text = st.text(max_size=300)
    seconds = st.floats(0.0, 1e9)
    option_value = st.one_of(st.booleans(), st.integers(protocol.INT64_MIN, protocol.INT64_MAX), finite,
                             text)
    property_test = settings(max_examples=60, deadline=None)

    def check_round_trip(msg):
        assert decode(encode(msg)) == msg

    @property_test
    @given(name, st.integers(1, protocol.MAX_CORES), st.lists(name, min_size=1, max_size=4, unique=True),
           st.text(max_size=20))
    def test_register_property(client_id, cores, backends, version):
        check_round_trip(Register(client_id=client_id, cores=cores, backends=backends, version=version))

    @property_test
    @given(name, st.floats(1e-3, protocol.MAX_HEARTBEAT_INTERVAL))
    def test_welcome_property(session, interval):
        check_round_trip(Welcome(session=session, heartbeat_interval=interval))

    @property_test
    @given(name, index, st.integers(1, 12), st.integers(1, 20), st.integers(1, 20), st.integers(0, 2**32),
           params)
    def test_frame_property(session, frame, K, H, W, seed, previous):
        masks = np.random.default_rng(seed).random((K, H, W)) < 0.5
        msg = Frame(session=session, frame=frame, cameras=camera_specs(circle_studio(K, W, H)),
                    silhouettes=packbits_masks(masks), previous_params=previous, body_scale=1.4,
                    body_fingerprint="0123456789abcdef")
        out = decode(encode(msg))
        assert out == msg
        np.testing.assert_array_equal(out.masks(), masks)

    @property_test
    @given(name, index, index, index, params,
           st.lists(st.sampled_from(JOB_NAMES), min_size=1, max_size=len(JOB_NAMES), unique=True),
           st.dictionaries(name, option_value, max_size=protocol.MAX_OPTIONS))
    def test_solve_property(session, frame, iteration, request, pose, chains, options):
        check_round_trip(Solve(session=session, frame=frame, iteration=iteration, request=request,
                               params=pose, chains=chains, options=options))

    @property_test
    @given(name, index, index, index, st.sampled_from(JOB_NAMES), params, finite, index, seconds, seconds)
    def test_result_property(session, frame, iteration, request, chain, pose, energy, evaluations, cpu, wall):
        check_round_trip(Result(session=session, frame=frame, iteration=iteration, request=request,
                                chain=chain, params=pose, energy=energy, energy_before=energy,
                                evaluations=evaluations, iterations=evaluations, cpu_seconds=cpu, wall_seconds=wall))

    @property_test
    @given(st.text(max_size=protocol.MAX_NAME_CHARS), name, text, index, index, index)
    def test_small_messages_property(session, code, message, frame, iteration, request):
        check_round_trip(Heartbeat(session=session))
        check_round_trip(Shutdown(reason=message, session=session))
        check_round_trip(Error(code=code, text=message, session=session, frame=frame, iteration=iteration,
                               request=request))

    @property_test
    @given(st.binary(max_size=200), st.integers(1, 3))
    def test_garbage_is_refused_with_a_reason(data, parts):
        try:
            decode([data] * parts)
        except ProtocolError as exc:
            assert exc.reason in REASONS
else:
    def test_properties_need_hypothesis():
        pytest.skip("hypothesis is not installed")
