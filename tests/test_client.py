"""The limb client against a scripted ROUTER on 127.0.0.1: registration, work, hostile input,
reconnects, shutdown and signals."""
import signal
import subprocess
import threading
import time

from dataclasses import replace

import numpy as np
import pytest
import zmq

from common.camera import circle_studio
from common.fitting import FitOptions, FrameData, solve_chain
from common.packing import packbits_masks
from common.protocol import (Error, Frame, Heartbeat, Register, Result, Shutdown, Solve, Welcome, camera_specs,
                             decode, encode)
from client.worker import Worker
from test_cluster_support import PY, ROOT, env, start_client, wait_for

HEARTBEAT = 1.0  # seconds, in the WELCOME: the scripted server does not beat, and must not seem gone
FAST_HEARTBEAT = 0.1  # seconds, where liveness is what is tested
RECV_TIMEOUT = 5000  # ms


class Router(zmq.Socket):
    endpoint: str = ""


@pytest.fixture
def router():
    ctx = zmq.Context()
    try:
        sock = ctx.socket(zmq.ROUTER, socket_class=Router)
        sock.linger = 0
        sock.rcvtimeo = RECV_TIMEOUT
        sock.endpoint = f"tcp://127.0.0.1:{sock.bind_to_random_port('tcp://127.0.0.1')}"
        yield sock
    finally:
        ctx.destroy(linger=0)


@pytest.fixture
def worker(model, router):
    w = Worker(model, router.endpoint, "w", reconnect_min=0.1, reconnect_max=0.2)
    t = threading.Thread(target=w.run, daemon=True)
    t.start()
    yield w
    w.stop()
    t.join(5)
    assert not t.is_alive()


def receive(router, want=None):
    """Next message (skipping heartbeats unless asked for): (identity, message)."""
    while True:
        ident, *frames = router.recv_multipart()
        msg = decode(frames)
        if want is Heartbeat or not isinstance(msg, Heartbeat):
            if want is not None:
                assert isinstance(msg, want), msg
            return ident, msg


def send(router, ident, msg):
    router.send_multipart([ident, *encode(msg)])


def register(router, session="s1", heartbeat=HEARTBEAT):
    ident, msg = receive(router, Register)
    assert msg.client_id == "w" and "cpu" in msg.backends
    send(router, ident, Welcome(session=session, heartbeat_interval=heartbeat))
    return ident


def frame_and_data(model, frame=0):
    studio = circle_studio(3, 64, 48)
    rng = np.random.default_rng(frame)
    masks = np.zeros((3, 48, 64), bool)
    masks[:, 10:40, 25:40] = True
    masks ^= rng.random(masks.shape) < 0.02
    start = np.zeros(35)
    start[2] = 0.9
    msg = Frame(session="s1", frame=frame, cameras=camera_specs(studio), silhouettes=packbits_masks(masks),
                previous_params=start.tolist(), body_scale=model.scale, body_fingerprint=model.fingerprint)
    return msg, FrameData(model, studio, masks), start


OPTIONS = FitOptions(max_evals_limb=30, max_evals_extremity=10, grid_steps=1)


@pytest.mark.timeout(30)
def test_solves_chains_with_the_engine_code(model, router, worker):
    ident = register(router)
    frame, data, start = frame_and_data(model)
    send(router, ident, frame)
    chains = ("left_arm", "right_leg")
    # iteration 0 of frame 0: the left arm's turn to be re-detected, which the client must do too
    send(router, ident, Solve(session="s1", frame=0, iteration=0, request=7, params=start.tolist(), chains=chains,
                              options=OPTIONS.to_wire()))
    results = [receive(router, Result)[1] for _ in chains]
    assert [r.chain for r in results] == list(chains)
    for r in results:
        expected = solve_chain(model, data, r.chain, start, OPTIONS, iteration=0)
        assert (r.session, r.frame, r.iteration, r.request) == ("s1", 0, 0, 7)
        assert np.array_equal(np.array(r.params), expected.params)
        assert r.energy == expected.energy and r.evaluations == expected.evaluations


@pytest.mark.timeout(30)
def test_heartbeats_at_the_welcome_interval(router, worker):
    ident = register(router, heartbeat=FAST_HEARTBEAT)
    t0 = time.monotonic()
    for _ in range(3):
        receive(router, Heartbeat)
        send(router, ident, Heartbeat(session="s1"))  # or it takes us for gone and registers again
    assert time.monotonic() - t0 < 10 * FAST_HEARTBEAT


@pytest.mark.timeout(30)
def test_drops_bad_messages_and_keeps_serving(model, router, worker):
    ident = register(router)
    frame, data, start = frame_and_data(model)
    bad = [[b"\xc1"], encode(Heartbeat()) + [b"x"], [encode(frame)[0], encode(frame)[1][:-3]],
           encode(Register(client_id="x", cores=1, backends=("cpu",), version="0")),
           encode(Solve(session="other", frame=0, iteration=0, request=1, params=start.tolist(),
                        chains=("left_arm",)))]
    for frames in bad:
        router.send_multipart([ident, *frames])
    send(router, ident, frame)
    send(router, ident, Solve(session="s1", frame=0, iteration=0, request=2, params=start.tolist(),
                              chains=("left_arm",), options=OPTIONS.to_wire()))
    _, result = receive(router, Result)
    assert result.request == 2
    assert worker.dropped == {"not_msgpack": 1, "frame_count": 1, "byte_length": 1, "unexpected": 1, "stale": 1}


@pytest.mark.timeout(30)
def test_asks_for_the_frame_it_lacks(model, router, worker):
    ident = register(router)
    _, _, start = frame_and_data(model)
    send(router, ident, Solve(session="s1", frame=3, iteration=0, request=5, params=start.tolist(),
                              chains=("head",)))
    _, err = receive(router, Error)
    assert err.code == "no_frame" and (err.frame, err.request) == (3, 5)


@pytest.mark.timeout(30)
def test_refuses_unknown_options(model, router, worker):
    ident = register(router)
    frame, _, start = frame_and_data(model)
    send(router, ident, frame)
    send(router, ident, Solve(session="s1", frame=0, iteration=0, request=9, params=start.tolist(),
                              chains=("head",), options={"warp_speed": 9}))
    _, err = receive(router, Error)
    assert err.code == "solve_failed" and "warp_speed" in err.text and err.request == 9


@pytest.mark.timeout(30)
def test_fits_the_actor_at_the_size_its_frame_gives(model, router, worker):
    """The server's actor is the body model at another size (chosen by the first frame, or
    --actor-height): the client, started with the model at its own size, fits the body at the
    FRAME's size, as one process would."""
    ident = register(router)
    actor = model.scaled(1.3)
    frame, data, start = frame_and_data(actor)
    send(router, ident, frame)
    send(router, ident, Solve(session="s1", frame=0, iteration=0, request=3, params=start.tolist(),
                              chains=("left_arm",), options=OPTIONS.to_wire()))
    _, r = receive(router, Result)
    expected = solve_chain(actor, data, "left_arm", start, OPTIONS, iteration=0)
    assert np.array_equal(np.array(r.params), expected.params) and r.energy == expected.energy
    at_own_size = solve_chain(model, FrameData(model, data.studio, data.masks), "left_arm", start, OPTIONS, iteration=0)
    assert r.energy != at_own_size.energy  # the size made a difference the test can see


@pytest.mark.timeout(30)
def test_refuses_a_frame_of_another_body(model, router, worker):
    """A client with other body data must not fit limbs for the server."""
    ident = register(router)
    frame, _, start = frame_and_data(model)
    other = replace(model, ellipsoid_radii=model.ellipsoid_radii * 1.1)  # other data at the same size
    send(router, ident, replace(frame, body_fingerprint=other.fingerprint))
    send(router, ident, Solve(session="s1", frame=0, iteration=0, request=4, params=start.tolist(),
                              chains=("head",)))
    _, err = receive(router, Error)
    assert err.code == "solve_failed" and err.request == 4
    assert other.fingerprint in err.text and model.fingerprint in err.text


@pytest.mark.timeout(30)
def test_registers_again_when_the_server_forgot_it(router, worker):
    ident = register(router)
    send(router, ident, Error(code="unregistered", text="who are you"))
    register(router, session="s2")
    wait_for(lambda: worker.session == "s2", 5, "the new session")


@pytest.mark.timeout(30)
def test_reconnects_when_the_server_goes_silent(router, worker):
    first = register(router, heartbeat=FAST_HEARTBEAT)
    # no heartbeats from us: after HEARTBEAT_LIVENESS intervals it opens a new connection
    second = register(router, session="s2")
    assert second != first
    wait_for(lambda: worker.session == "s2" and worker.sessions == 2, 5, "the second registration")


@pytest.mark.timeout(30)
def test_shutdown_ends_the_run_with_a_goodbye(model, router):
    w = Worker(model, router.endpoint, "w")
    outcome = []
    t = threading.Thread(target=lambda: outcome.append(w.run()), daemon=True)
    t.start()
    ident = register(router)
    send(router, ident, Shutdown(reason="done", session="s1"))
    _, bye = receive(router, Error)
    assert bye.code == "client_exit"
    t.join(5)
    assert outcome == ["shutdown"]


@pytest.mark.timeout(30)
def test_sigterm_mid_solve_exits_within_seconds(model, router, tmp_path):
    log = tmp_path / "client.log"
    proc = start_client(router.endpoint, "w", log, "-v", "--test-stall", "60")
    try:
        ident = register(router)
        frame, _, start = frame_and_data(model)
        send(router, ident, frame)
        send(router, ident, Solve(session="s1", frame=0, iteration=0, request=1, params=start.tolist(),
                                  chains=("left_leg",)))
        wait_for(lambda: "solving frame" in log.read_text(), 10, "the client to take the request")
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert time.monotonic() - t0 < 10
        _, bye = receive(router, Error)
        assert bye.code == "client_exit"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_bad_curve_keys_are_a_usage_error(tmp_path):
    proc = subprocess.run([PY, "-m", "client", "--connect", "tcp://127.0.0.1:1", "--curve-keys", str(tmp_path)],
                          cwd=ROOT, env=env(), capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2 and "--curve-keys" in proc.stderr


def test_mocap_client_is_python_m_client():
    proc = subprocess.run([PY, "-m", "server.cli", "client", "--help"], cwd=ROOT, env=env(), capture_output=True,
                          text=True, timeout=30)
    assert proc.returncode == 0 and "--connect" in proc.stdout


def test_a_bad_address_is_a_usage_error():
    proc = subprocess.run([PY, "-m", "client", "--connect", "bogus://x"], cwd=ROOT, env=env(), capture_output=True,
                          text=True, timeout=30)
    assert proc.returncode == 2 and "bogus://x" in proc.stderr
