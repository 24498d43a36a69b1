"""Faults with real processes on 127.0.0.1: each run still ends with every frame once and the
single-process poses."""
import json
import signal
import subprocess
import time

import numpy as np
import pytest

from test_cluster_support import (FRAMES, HEARTBEAT, PY, ROOT, TRACKING_ONLY, alive, children, env, free_port, poses, records,
                                  reference_fit, start_client, start_server, stop, wait_for)

TOLERANCE = 1e-9
STOP_SECONDS = 10.0  # what SIGTERM may take, at most


@pytest.fixture(scope="module")
def seq_path(small_sequence):
    return small_sequence


@pytest.fixture(scope="module")
def reference(seq_path, tmp_path_factory):
    return reference_fit(seq_path, tmp_path_factory.mktemp("faults") / "single")


def check_complete(out, reference):
    frames = [r["frame"] for r in records(out)]
    assert frames == list(range(FRAMES)), frames  # every frame, once, in order
    assert np.abs(poses(out) - reference).max() <= TOLERANCE


def summary(out) -> dict:
    return json.loads((out / "summary.json").read_text())


def log_has(path, text: str) -> bool:
    return path.exists() and text in path.read_text()


@pytest.mark.timeout(90)
def test_client_killed_mid_frame(seq_path, reference, tmp_path):
    port, out = free_port(), tmp_path / "out"
    endpoint = f"tcp://127.0.0.1:{port}"
    server = start_server(seq_path, out, port, tmp_path / "server.log", "--min-clients", "2")
    good = start_client(endpoint, "good", tmp_path / "good.log")
    # this one holds its first chain long enough to be killed while it has it
    doomed = start_client(endpoint, "doomed", tmp_path / "doomed.log", "-v", "--test-stall", "30")
    try:
        wait_for(lambda: log_has(tmp_path / "doomed.log", "solving frame"), 30, "the doomed client to get a chain")
        doomed.send_signal(signal.SIGKILL)
        assert server.wait(60) == 0, (tmp_path / "server.log").read_text()
        good.wait(STOP_SECONDS)  # released by the server's SHUTDOWN
    finally:
        stop([server, good, doomed])
    check_complete(out, reference)
    timing = summary(out)["timing"]
    assert timing["resent"] >= 1  # the killed client's chain was solved by another
    # its loss is noticed once its silence outlasts the heartbeat timeout, which a three-frame
    # run can finish before: then after the summary is written, still said in the log
    assert timing["lost_clients"] >= 1 or log_has(tmp_path / "server.log", "client doomed silent")


@pytest.mark.timeout(90)
def test_client_that_stalls(seq_path, reference, tmp_path):
    port, out = free_port(), tmp_path / "out"
    endpoint = f"tcp://127.0.0.1:{port}"
    server = start_server(seq_path, out, port, tmp_path / "server.log", "--min-clients", "2",
                          "--client-timeout", "1")
    good = start_client(endpoint, "good", tmp_path / "good.log")
    slow = start_client(endpoint, "slow", tmp_path / "slow.log", "--test-stall", "3")
    try:
        assert server.wait(60) == 0, (tmp_path / "server.log").read_text()
    finally:
        stop([server, good, slow])
    check_complete(out, reference)
    timing = summary(out)["timing"]
    assert timing["stalls"] >= 1 and timing["lost_clients"] == 0
    assert next(p for p in timing["processes"] if p["name"] == "slow")["stalls"] >= 1


@pytest.mark.timeout(120)
def test_server_killed_and_resumed(seq_path, reference, tmp_path):
    port, out = free_port(), tmp_path / "out"
    endpoint = f"tcp://127.0.0.1:{port}"
    slow = ("--test-stall", "0.3", "--test-stall-requests", "1000")  # frames slow enough to kill in between
    server = start_server(seq_path, out, port, tmp_path / "server.log", "--min-clients", "2")
    clients = [start_client(endpoint, f"c{i}", tmp_path / f"c{i}.log", *slow) for i in (1, 2)]
    try:
        wait_for(lambda: len(records(out)) >= 1, 60, "the first frame")
        server.send_signal(signal.SIGKILL)
        server.wait(10)
        assert len(records(out)) < FRAMES, "the run ended before the kill: slow it down"
        server = start_server(seq_path, out, port, tmp_path / "server.log", "--min-clients", "2", "--resume")
        assert server.wait(90) == 0, (tmp_path / "server.log").read_text()
        for c in clients:
            c.wait(STOP_SECONDS)  # they reconnected, registered again, and were released at the end
    finally:
        stop([server, *clients])
    check_complete(out, reference)
    s = summary(out)
    assert 0 < s["frames_fitted_this_run"] < FRAMES
    assert all("registered with" in (tmp_path / f"c{i}.log").read_text().split("silent")[-1] for i in (1, 2))


LATE_CLIENT = """
import sys, time
from pathlib import Path
import client.__main__ as client_main
from common.objective import compile_kernels
compile_kernels()
go, endpoint = Path(sys.argv[1]), sys.argv[2]
deadline = time.monotonic() + 60
while not go.exists() and time.monotonic() < deadline:
    time.sleep(0.01)
sys.exit(client_main.main(["--connect", endpoint, "--id", "late", "--reconnect-min", "0.2", "--exit-with-parent"]))
"""


@pytest.mark.timeout(90)
def test_client_joins_late(seq_path, reference, tmp_path):
    port, out = free_port(), tmp_path / "out"
    endpoint = f"tcp://127.0.0.1:{port}"
    server = start_server(seq_path, out, port, tmp_path / "server.log", "--min-clients", "1")
    early = start_client(endpoint, "early", tmp_path / "early.log", "-v", "--test-stall", "0.8",
                         "--test-stall-requests", "1000")
    # the late client's interpreter, imports and kernels loaded before the run starts, so that it
    # joins as soon as the run is under way: a client started from nothing then took longer to
    # start than the three frames' run on a loaded machine
    go = tmp_path / "go"
    with open(tmp_path / "late.log", "w") as fh:
        late = subprocess.Popen([PY, "-c", LATE_CLIENT, str(go), endpoint], cwd=ROOT, env=env(), stdout=fh, stderr=fh)
    try:
        wait_for(lambda: log_has(tmp_path / "early.log", "solving frame"), 60, "the run to start")
        go.touch()
        assert server.wait(60) == 0, (tmp_path / "server.log").read_text()
    finally:
        stop([p for p in (server, early, late) if p])
    check_complete(out, reference)
    processes = {p["name"]: p for p in summary(out)["timing"]["processes"]}
    assert processes["late"]["chains"] >= 1, processes


@pytest.mark.timeout(90)
def test_the_sigterm_guard_off_the_main_thread_is_no_guard():
    """A batch's Dask worker runs mocap fit on a thread of its own, where no signal handler can
    be set: the block runs as it is."""
    import threading

    from server.local_cluster import terminate_on_sigterm

    ran, failed = [], []

    def fit_on_a_worker_thread():
        try:
            with terminate_on_sigterm():
                ran.append(True)
        except ValueError as exc:  # "signal only works in main thread"
            failed.append(exc)

    worker = threading.Thread(target=fit_on_a_worker_thread)
    worker.start()
    worker.join(10)
    assert ran == [True] and failed == []


def test_sigterm_stops_a_single_process_fit_as_ctrl_c(seq_path, tmp_path):
    """A job scheduler's SIGTERM to a single-process fit: exit 130 and the line that says what
    was kept, as Ctrl-C (not a silent 143)."""
    out = tmp_path / "out"
    cmd = [PY, "-m", "server.cli", "fit", str(seq_path), "--out", str(out), "--quiet", "--refine-passes", "1"]
    with open(tmp_path / "fit.log", "w") as log:
        fit = subprocess.Popen(cmd, cwd=ROOT, env=env(), stdout=log, stderr=log)
    try:
        wait_for(lambda: len(records(out)) >= 1, 60, "the first frame")
        fit.send_signal(signal.SIGTERM)
        assert fit.wait(STOP_SECONDS) == 130
    finally:
        stop([fit])
    assert (tmp_path / "fit.log").read_text().strip().endswith(
        f"mocap fit: interrupted; the frames fitted are kept in {out}, and the same command with --resume continues")


def test_sigterm_stops_everything_and_resume_finishes(seq_path, reference, tmp_path):
    out = tmp_path / "out"
    cmd = [PY, "-m", "server.cli", "fit", str(seq_path), "--out", str(out), "--clients", "2",
           "--heartbeat", str(HEARTBEAT), "--quiet", *TRACKING_ONLY]
    with open(tmp_path / "fit.log", "w") as log:
        fit = subprocess.Popen(cmd, cwd=ROOT, env=env(), stdout=log, stderr=log)
    try:
        wait_for(lambda: len(records(out)) >= 1, 60, "the first frame")
        kids = children(fit.pid)
        assert len(kids) == 2
        t0 = time.monotonic()
        fit.send_signal(signal.SIGTERM)
        fit.wait(STOP_SECONDS)
        wait_for(lambda: not any(alive(k) for k in kids), STOP_SECONDS - (time.monotonic() - t0), "the clients to exit")
        assert time.monotonic() - t0 < STOP_SECONDS
        kept = records(out)
        assert 1 <= len(kept) <= FRAMES
        with open(tmp_path / "fit.log", "a") as log:
            resumed = subprocess.run([*cmd, "--resume"], cwd=ROOT, env=env(), stdout=log, stderr=log,
                                                   timeout=60)
        assert resumed.returncode == 0, (tmp_path / "fit.log").read_text()
    finally:
        stop([fit])
    check_complete(out, reference)
