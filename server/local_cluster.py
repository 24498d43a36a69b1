"""A cluster on this machine (``mocap fit --clients N``): the server and N client processes,
started, waited for and stopped in order; and the cluster's command-line flags."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

from common import argtypes
from common.errors import UserError
from common.fitting import FitOptions
from server.trust import LOOPBACK_BIND, NETWORK_BIND
from server.cluster import (CLIENT_TIMEOUT, DEADLINE_FACTOR, DEADLINE_FLOOR, HEARTBEAT_INTERVAL,
                            HEARTBEAT_LIVENESS, LOCAL_BIND, ClusterSolver)

CLIENT_START_TIMEOUT = 60.0  # seconds for local clients to start and register
CLIENT_STOP_TIMEOUT = 5.0  # seconds a local client gets to exit after SIGTERM


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that ``finally`` blocks run (see ``terminate_on_sigterm``)."""


@contextmanager
def terminate_on_sigterm():
    """Within the block, SIGTERM raises ``Terminated`` in the main thread; the old handler after.
    Off the main thread (a fit run by a batch's Dask worker) signals cannot be caught: nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _project_root() -> Path:
    return Path(__file__).resolve().parent.parent


class LocalCluster:
    """A ClusterSolver on 127.0.0.1 (random port) and ``n`` client subprocesses (``python -m client``).

    ``with LocalCluster(...) as solver:`` waits until every client has registered; on leaving
    (normally, on an error or on Ctrl-C/SIGTERM) it sends SHUTDOWN, then SIGTERM, then SIGKILL
    to clients still there after ``CLIENT_STOP_TIMEOUT``.
    """

    def __init__(self, options: FitOptions, clients: int,
                 heartbeat_interval: float = HEARTBEAT_INTERVAL, client_timeout: float = CLIENT_TIMEOUT,
                 client_args: tuple[str, ...] = (), threads: int = 0):
        self.options, self.n, self.threads = options, clients, threads
        self.heartbeat_interval, self.client_timeout = heartbeat_interval, client_timeout
        self.client_args = client_args
        self.solver: ClusterSolver | None = None
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> ClusterSolver:
        self.solver = ClusterSolver(self.options, bind=LOCAL_BIND, heartbeat_interval=self.heartbeat_interval,
                                    client_timeout=self.client_timeout, threads=self.threads)
        try:
            env = dict(os.environ)
            env["PYTHONPATH"] = os.pathsep.join(p for p in (str(_project_root()), env.get("PYTHONPATH")) if p)
            for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
                env.setdefault(var, "1")  # one core per client: no thread oversubscription
            for i in range(self.n):
                self.procs.append(subprocess.Popen(
                    [sys.executable, "-m", "client", "--connect", self.solver.endpoint, "--id", f"local-{i + 1}",
                     "--quiet", "--exit-with-parent", "--reconnect-min", "0.2", *self.client_args],
                    # own sessions: a terminal's Ctrl-C reaches only us, and we stop them in order;
                    # the kernel's autogroup scheduler also shares the CPU out per session, so each
                    # client counts as a machine of its own, as in the paper's cluster
                    env=env, stdin=subprocess.DEVNULL, start_new_session=True))
            self.solver.wait_for_clients(self.n, CLIENT_START_TIMEOUT, check=self._check_alive)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self.solver

    def _check_alive(self) -> None:
        for i, p in enumerate(self.procs):
            if p.poll() is not None:
                raise UserError(f"local client {i + 1} exited with status {p.returncode} before registering")

    def __exit__(self, *exc) -> None:
        if self.solver is not None:
            self.solver.close(shutdown="run finished")
        stop_processes(self.procs, CLIENT_STOP_TIMEOUT)


def stop_processes(procs: list, timeout: float) -> None:
    """SIGTERM the ones still running, wait up to ``timeout`` in all, SIGKILL the rest."""
    deadline = time.monotonic() + timeout
    for p in procs:
        if p.poll() is None:
            # they may be exiting on SHUTDOWN already
            try:
                p.wait(max(0.0, min(0.5, deadline - time.monotonic())))
            except subprocess.TimeoutExpired:
                p.terminate()
    for p in procs:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def add_cluster_arguments(p, server: bool) -> None:
    """Command-line flags of the cluster: ``mocap server`` (server=True) or ``mocap fit --clients``."""
    if server:
        p.add_argument("--bind", type=argtypes.zmq_address, default=None, metavar="ADDRESS",
                       help=f"ROUTER address (default: {LOOPBACK_BIND}, this machine's clients only; with "
                            f"--curve-keys {NETWORK_BIND}, every interface); without --curve-keys only a loopback "
                            "or ipc:// address, unless --insecure")
        p.add_argument("--min-clients", type=argtypes.count(0), default=1,
                       help="clients to wait for before the first frame (default 1; 0: start at once)")
        p.add_argument("--curve-keys", type=Path, default=None, metavar="DIR",
                       help="CURVE: DIR/server.key_secret, allowed client keys in DIR/clients/*.key (the folder "
                            "mocap keys DIR makes)")
        p.add_argument("--insecure", action="store_true",
                       help="bind a network address without CURVE: any host that reaches it can join")
    p.add_argument("--client-timeout", type=argtypes.seconds, default=CLIENT_TIMEOUT,
                   help=f"seconds a chain or hop may take on a client at most before it is re-sent (default "
                        f"{CLIENT_TIMEOUT:g}); once solves are measured, {DEADLINE_FACTOR:g} times their median, "
                        f"at least {DEADLINE_FLOOR:g}")
    p.add_argument("--heartbeat", type=argtypes.real(0.001, 3600.0), default=HEARTBEAT_INTERVAL,
                   help=f"heartbeat interval, seconds (default {HEARTBEAT_INTERVAL:g}); a peer silent for "
                        f"{HEARTBEAT_LIVENESS} intervals counts as gone")
