"""Helpers for the cluster and client tests (no tests here): a reference single-process fit,
in-thread workers and subprocesses on 127.0.0.1. The sequence is conftest's ``small_sequence``."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable
HEARTBEAT = 0.3  # seconds: fast failure detection in tests with client processes
# in-thread workers share the GIL with the server's fits: a slower beat, so none is taken for dead
THREAD_HEARTBEAT = 1.0
FRAMES = 3  # conftest.SMALL_FRAMES
# faults are tested while tracking; the refinement passes solve through the same solver, and
# tests/test_cluster.py checks that they too give the single process's poses
TRACKING_ONLY = ("--refine-passes", "0")


def reference_fit(seq_path: Path, out: Path, max_frames: int | None = None) -> np.ndarray:
    """(F, 35) poses of the single-process fit with default options (what the CLI uses), tracking only."""
    from common.body import load_body_model
    from common.fitting import FitOptions
    from common.sequence import load_sequence
    from server.session import LocalSolver, run_fit

    model = load_body_model()
    options = FitOptions(refine_passes=0)
    run_fit(model, load_sequence(seq_path), out, options, LocalSolver(model, options), max_frames=max_frames)
    return poses(out)


def records(out: Path) -> list[dict]:
    """The complete records of a result's poses.jsonl, which a running fit may be appending to:
    its last line counts once its newline is written (``server.results.read_done_frames``)."""
    path = Path(out) / "poses.jsonl"
    return [json.loads(line) for line in path.read_text().split("\n")[:-1]] if path.exists() else []


def poses(out: Path) -> np.ndarray:
    return np.array([r["params"] for r in records(out)])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate, timeout: float, what: str, poll: float = 0.02):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


@contextmanager
def thread_workers(model, endpoint: str, n: int, **kwargs):
    """``n`` in-process Workers (threads) connected to ``endpoint``; stopped and joined on exit."""
    from client.worker import Worker

    workers = [Worker(model, endpoint, f"t{i + 1}", reconnect_min=0.2, **kwargs) for i in range(n)]
    threads = [threading.Thread(target=w.run, daemon=True) for w in workers]
    for t in threads:
        t.start()
    try:
        yield workers
    finally:
        for w in workers:
            w.stop()
        for t in threads:
            t.join(5)
        assert not any(t.is_alive() for t in threads), "a worker thread did not stop"


def env() -> dict:
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), e.get("PYTHONPATH")) if p)
    e.setdefault("OMP_NUM_THREADS", "1")
    return e


def start_client(endpoint: str, name: str, log: Path, *extra: str) -> subprocess.Popen:
    with open(log, "w") as fh:
        return subprocess.Popen([PY, "-m", "client", "--connect", endpoint, "--id", name, "--reconnect-min", "0.2",
                                 "--exit-with-parent", *extra], cwd=ROOT, env=env(), stdout=fh, stderr=fh)


def start_server(seq: Path, out: Path, port: int, log: Path, *extra: str) -> subprocess.Popen:
    with open(log, "a") as fh:
        return subprocess.Popen([PY, "-m", "server.cli", "server", str(seq), "--out", str(out), "--bind",
                                 f"tcp://127.0.0.1:{port}", "--heartbeat", str(HEARTBEAT), "--quiet", *TRACKING_ONLY,
                                 *extra],
                                cwd=ROOT, env=env(), stdout=fh, stderr=fh)


def stop(procs) -> None:
    """Make sure nothing a test started outlives it."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGKILL)
        p.wait(10)


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def children(pid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]
