"""Hostile input to a running server: every bad message is dropped, counted and logged once, and
the server goes on serving its clients (the poses still match the single-process fit)."""
import logging
import math
import threading
import time

import msgpack
import numpy as np
import pytest
import zmq
import zmq.auth

from common.fitting import FitOptions
from common.packing import packbits_masks
from common.protocol import (MAX_CLIENT_MESSAGE_BYTES, MAX_HEADER_BYTES, PROTOCOL_VERSION, Frame, Heartbeat, Register,
                             camera_specs, encode)
from common.camera import circle_studio
from common.sequence import load_sequence
from client.worker import CurveKeys
from server.cluster import LOCAL_BIND, ClusterSolver
from server.trust import create_curve_keys
from server.session import run_fit
from test_cluster_support import HEARTBEAT, THREAD_HEARTBEAT, poses, reference_fit, thread_workers, wait_for

TOLERANCE = 1e-9
PARAMS = [0.0] * 35


def result_header(**overrides) -> dict:
    header = {"v": PROTOCOL_VERSION, "type": "result", "session": "s", "frame": 0, "iteration": 0, "request": 0,
              "chain": "left_arm", "params": PARAMS, "energy": 1.0, "energy_before": 2.0, "evaluations": 1,
              "iterations": 1, "cpu_seconds": 0.1,
              "wall_seconds": 0.1}
    header.update(overrides)
    return header


def pack(header: dict) -> bytes:
    return msgpack.packb(header, use_bin_type=True)


def frame_message() -> list:
    masks = np.zeros((2, 8, 8), bool)
    return encode(Frame(session="s", frame=0, cameras=camera_specs(circle_studio(2, 8, 8)),
                        silhouettes=packbits_masks(masks), previous_params=PARAMS, body_scale=1.0,
                        body_fingerprint="0123456789abcdef"))


BAD_MESSAGES = {
    "not_msgpack": [b"\xc1 this is not msgpack"],
    "version": [pack({"v": PROTOCOL_VERSION + 1, "type": "heartbeat", "session": "", "frame": 0, "iteration": 0,
                      "request": 0})],
    "frame_count": encode(Heartbeat()) + [b"an extra frame"],
    "byte_length": [frame_message()[0], frame_message()[1][:-1]],
    "non_finite": [pack(result_header(params=[math.nan] + PARAMS[1:]))],
    "too_large": encode(Heartbeat()) + [b"x", b"y"],  # more frames than any message has
    "unknown_type": [pack({"v": PROTOCOL_VERSION, "type": "pose_please", "session": "", "frame": 0,
                           "iteration": 0, "request": 0})],
    "bad_field": [pack(result_header(chain="tail"))],
}


@pytest.fixture(scope="module")
def seq_path(small_sequence):
    return small_sequence


@pytest.fixture(scope="module")
def reference(seq_path, tmp_path_factory):
    return reference_fit(seq_path, tmp_path_factory.mktemp("messages") / "single", max_frames=1)


def raw_dealer(ctx: zmq.Context, endpoint: str, **curve) -> zmq.Socket:
    s = ctx.socket(zmq.DEALER)
    s.linger = 0
    s.rcvtimeo = 1000
    for k, v in curve.items():
        setattr(s, k, v)
    s.connect(endpoint)
    return s


def fit_one_frame(model, seq_path, solver, out) -> np.ndarray:
    run_fit(model, load_sequence(seq_path), out, FitOptions(), solver, max_frames=1)
    return poses(out)


@pytest.mark.timeout(60)
def test_bad_messages_are_dropped_counted_logged_once(model, seq_path, reference, tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="server.cluster")
    solver = ClusterSolver(FitOptions(), bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    ctx = zmq.Context()
    try:
        with thread_workers(model, solver.endpoint, 2):
            solver.wait_for_clients(2, timeout=10)
            attacker = raw_dealer(ctx, solver.endpoint)
            for _ in range(2):
                for frames in BAD_MESSAGES.values():
                    attacker.send_multipart(frames)
            # many frames, each under the server's MAXMSGSIZE: refused by decode
            attacker.send_multipart([encode(Heartbeat())[0]] + [b"\0" * MAX_CLIENT_MESSAGE_BYTES] * 20)
            wait_for(lambda: sum(solver.stats()["dropped"].values()) >= 2 * len(BAD_MESSAGES) + 1, 10,
                     "the server to read the bad messages")
            # a well-formed message from a peer that never registered is refused too, with an answer
            attacker.send_multipart(encode(Heartbeat(session="nobody")))
            reply = attacker.recv_multipart()
            assert b"unregistered" in reply[0]
            # one frame over zmq's MAXMSGSIZE (a header over MAX_HEADER_BYTES too): zmq closes that
            # connection; the others go on
            oversized = raw_dealer(ctx, solver.endpoint)
            disconnects = solver.stats()["disconnects"]
            oversized.send_multipart([pack({"v": PROTOCOL_VERSION, "type": "heartbeat",
                                            "pad": b"x" * (MAX_HEADER_BYTES + 1)})])
            wait_for(lambda: solver.stats()["disconnects"] > disconnects, 10, "zmq to drop the oversized peer")
            got = fit_one_frame(model, seq_path, solver, tmp_path)
            stats = solver.stats()
    finally:
        ctx.destroy(linger=0)
        solver.close(shutdown="done")
    dropped = stats["dropped"]
    for reason in BAD_MESSAGES:
        assert dropped.get(reason, 0) >= 2, (reason, dropped)
    assert dropped["too_large"] == 3 and dropped["unregistered"] == 1
    messages = [r.getMessage() for r in caplog.records]
    for reason in [*BAD_MESSAGES, "unregistered"]:
        assert sum(f"({reason})" in m for m in messages) == 1, (reason, messages)
    assert np.abs(got - reference).max() <= TOLERANCE
    assert stats["resent"] == 0 and stats["lost_clients"] == 0


@pytest.mark.timeout(60)
def test_forged_and_stale_results_are_dropped(model, seq_path, reference, tmp_path):
    solver = ClusterSolver(FitOptions(), bind=LOCAL_BIND, heartbeat_interval=HEARTBEAT)
    ctx = zmq.Context()
    try:
        with thread_workers(model, solver.endpoint, 1):
            solver.wait_for_clients(1, timeout=10)
            rogue = raw_dealer(ctx, solver.endpoint)
            rogue.send_multipart(encode(Register(client_id="rogue", cores=1, backends=("cpu",), version="0")))
            assert b"welcome" in rogue.recv_multipart()[0]
            # a registered peer answering a request nobody sent it, for an old session
            rogue.send_multipart([pack(result_header(session="old-session", request=12345))])
            wait_for(lambda: solver.stats()["dropped"].get("stale"), 10, "the stale result to be dropped")
            rogue.close(linger=0)  # it never answers a SOLVE: it is dropped after the liveness timeout
            got = fit_one_frame(model, seq_path, solver, tmp_path)
    finally:
        ctx.destroy(linger=0)
        solver.close(shutdown="done")
    assert np.abs(got - reference).max() <= TOLERANCE


@pytest.mark.timeout(60)
def test_curve_lets_only_allowed_keys_in(model, seq_path, reference, tmp_path):
    keys = create_curve_keys(tmp_path / "keys")
    (tmp_path / "intruder").mkdir()
    zmq.auth.create_certificates(tmp_path / "intruder", "client")
    allowed = CurveKeys.load(keys)
    intruder_public, intruder_secret = zmq.auth.load_certificate(tmp_path / "intruder" / "client.key_secret")
    solver = ClusterSolver(FitOptions(), bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT,
                           curve_keys=keys)
    ctx = zmq.Context()
    try:
        with thread_workers(model, solver.endpoint, 1, curve=allowed) as (good,), \
                thread_workers(model, solver.endpoint, 1,
                               curve=CurveKeys(intruder_public, intruder_secret, allowed.server)) as (bad,):
            solver.wait_for_clients(1, timeout=10)
            plain = raw_dealer(ctx, solver.endpoint)  # no CURVE at all
            plain.send_multipart(encode(Register(client_id="plain", cores=1, backends=("cpu",), version="0")))
            wait_for(lambda: solver.stats()["dropped"].get("unauthenticated"), 10, "the intruder to be refused")
            wait_for(lambda: solver.stats()["dropped"].get("handshake"), 10, "the plain peer to be refused")
            with pytest.raises(zmq.Again):
                plain.recv_multipart()  # it gets nothing, not even an error
            got = fit_one_frame(model, seq_path, solver, tmp_path)
            assert bad.sessions == 0 and good.sessions == 1
            assert solver.client_count() == 1
    finally:
        ctx.destroy(linger=0)
        solver.close(shutdown="done")
    assert np.abs(got - reference).max() <= TOLERANCE


def test_curve_keys_folder_is_checked(model, tmp_path):
    from common.errors import UserError

    with pytest.raises(UserError, match="server.key_secret"):
        ClusterSolver(FitOptions(), bind=LOCAL_BIND, curve_keys=tmp_path)


@pytest.mark.timeout(60)
def test_a_client_that_fails_a_chain_gets_no_more_work(model, seq_path, reference, tmp_path):
    from common.protocol import Error, Solve, decode

    solver = ClusterSolver(FitOptions(), bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    ctx = zmq.Context()
    solves, done = [], threading.Event()

    def failing_client(sock):
        next_beat = 0.0
        while not done.is_set():
            if time.monotonic() > next_beat:
                sock.send_multipart(encode(Heartbeat(session=solver.session)))
                next_beat = time.monotonic() + THREAD_HEARTBEAT / 2
            if sock.poll(20):
                msg = decode(sock.recv_multipart())
                if isinstance(msg, Solve):
                    solves.append(msg)
                    sock.send_multipart(encode(Error(code="solve_failed", text="no GPU here", session=msg.session,
                                                     frame=msg.frame, iteration=msg.iteration,
                                                     request=msg.request)))

    try:
        failing = raw_dealer(ctx, solver.endpoint)
        failing.send_multipart(encode(Register(client_id="failing", cores=1, backends=("cpu",), version="0")))
        assert b"welcome" in failing.recv_multipart()[0]
        thread = threading.Thread(target=failing_client, args=(failing,), daemon=True)
        thread.start()
        with thread_workers(model, solver.endpoint, 1):
            solver.wait_for_clients(2, timeout=10)
            got = fit_one_frame(model, seq_path, solver, tmp_path)
            stats = solver.stats()
        done.set()
        thread.join(5)
    finally:
        done.set()
        ctx.destroy(linger=0)
        solver.close(shutdown="done")
    # one resend for the failed chain; on a loaded machine the good client can also overrun
    # the client timeout (a stall), which may resend its chain too
    assert len(solves) == 1 and 1 <= stats["resent"] <= 1 + stats["stalls"] and stats["lost_clients"] == 0
    assert np.abs(got - reference).max() <= TOLERANCE


def test_cluster_settings_are_checked(model):
    from common.errors import UserError

    with pytest.raises(UserError, match="--heartbeat"):
        ClusterSolver(FitOptions(), bind=LOCAL_BIND, heartbeat_interval=0.0)
    with pytest.raises(UserError, match="--client-timeout"):
        ClusterSolver(FitOptions(), bind=LOCAL_BIND, client_timeout=-1.0)
