"""The server side of the fitting cluster (Theobalt et al. 2003, section 5) over ZeroMQ.

``ClusterSolver`` is the ``Solver`` of ``server.session.run_fit`` that hands limb chains to
clients (``python -m client``) connected to a ROUTER socket. Per frame it sends every client
the packed silhouettes once (FRAME; again where a frame's masks changed, as when foreground no
pose explains is cleared once a take is fitted); per iteration it sends each idle client one chain to
solve from the current pose (SOLVE) and gathers the RESULTs, while the caller fits the head.

Work sharing: chains wait in a queue and go one at a time to idle clients, longest idle
first, so with fewer clients than limbs a client takes several chains in turn. With more
clients than limbs the spare ones stand by (and take over from a client that fails). When a
chain is queued and no client is free, the server solves it itself after the head: the
server is worker zero, and with no clients at all this is the single-process mode.
The limbs are solved Jacobi-style, so who solves a chain never changes its result. A
refinement's hops (``common.fitting.hop_fit``) go out the same way, a few side by side.
A round that the server's own cores (``threads``) would solve sooner than the clients stays on
the server (``short_rounds``): its jobs' CPU seconds over those cores against one job's plus a
hand-over, each kind of job's CPU seconds and the hand-overs (a result's round trip less the
client's solve) measured as the run goes. A polishing round's four limb solves of about 3 ms
would otherwise wait longer for the messages and the wake-ups on both sides. The seconds
clients report decide only where jobs run, never a result.

Reliability (zguide's Paranoid Pirate, adapted):
 - heartbeats both ways every ``heartbeat_interval``; a client silent for ``HEARTBEAT_LIVENESS``
   intervals is dropped and its chain queued again; clients do the same with the server and
   reconnect with backoff, then register again (a restarted server answers an unknown peer
   with ERROR "unregistered", which makes it register at once);
 - a chain not back within its deadline is queued again and its client gets no new work until
   it answers. The deadline is ``DEADLINE_FACTOR`` times the median of the measured solve times
   of that kind of job (round trips of accepted results, and the server's own solves), at least
   ``DEADLINE_FLOOR``, at most ``client_timeout``, which is also the deadline before anything
   is measured; while it waits on a kind nothing has measured, the server solves one job of
   it itself, so a new kind of job costs a measured deadline, not ``client_timeout``;
 - a chain queued again (its client stalled, failed or left, or its result was refused) goes
   to a client that has delivered accepted work, or the server solves it: a crowd of new peers
   that never answer costs one deadline per round, not one per peer;
 - the first result for a chain wins; results are matched by (session, frame, iteration,
   request id, chain, sender) and everything else (late, duplicate, stale) is dropped;
 - no result is used unchecked: the caller's thread scores its parameters once
   (``score_job``, the energies ``solve_job`` reports); a result whose energies differ from
   its claim, or that moved parameters outside its chain, is refused (``stats()["rejected"]``,
   logged once per client), its chain queued again, and its sender gets no more work;
 - every message goes through ``common.protocol.decode``; bad ones are logged once per reason,
   counted in ``stats()["dropped"]`` and dropped; a message of more than ``MAX_PARTS`` frames
   also makes the server forget its sender. ``MAXMSGSIZE`` is the largest message a client
   sends (``MAX_CLIENT_MESSAGE_BYTES``): zmq closes a connection with a larger frame before
   buffering it (counted as ``disconnects``, zmq gives no reason). zmq buffers every frame
   of a message before it delivers the first, so only CURVE bounds what an unknown peer can
   make the server hold (docs/cluster.md);
 - FRAME carries the actor's size (its clients fit the body at it, whatever size they started
   with) and the body's fingerprint at that size: a client with other body data fails the SOLVEs
   of that frame and gets no more work, rather than fit limbs of another body;
 - CURVE: ``curve_keys`` names a folder with ``server.key_secret`` and ``clients/``, the public
   keys allowed to connect; other peers fail the handshake and get nothing. Without it only a
   loopback or ipc address may be bound, unless ``insecure`` (``check_bind``).

Threads: a broker thread owns the socket and does all I/O, heartbeats and time-outs; the
caller's thread queues work, checks results and waits for them (or solves a chain itself), so
the clients hear from the server while it fits the torso and head.

One module of about 930 lines: ``ClusterSolver`` is one state machine whose broker thread and
caller thread share its lock and round state; what it trusts is ``server.trust``, the local
cluster ``server.local_cluster``.
"""
from __future__ import annotations

import hashlib
import logging
import queue
import secrets
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils.monitor import recv_monitor_message

from common.energy import whole_energy
from common.errors import UserError
from common.fitting import (
    EVOLVE_JOBS, HOP_JOBS, REDETECT_ROUND, ChainResult, FitOptions, FrameData, redetects,
)
from common.helping_pool import HelpingPool
from common.search import FIT_JOBS, job_options, job_starts, solve_job, solve_locally
from server.threads import resolve_threads
from server.trust import check_bind, check_result, default_bind, server_keys
from common.packing import packbits_masks
from common.protocol import (
    MAX_CLIENT_MESSAGE_BYTES, MAX_PARTS, Error, Frame, Heartbeat, ProtocolError, Register, Result, Shutdown, Solve,
    Welcome, camera_specs, decode, encode,
)

LOCAL_BIND = "tcp://127.0.0.1:*"  # a random free port on the loopback interface
HEARTBEAT_INTERVAL = 1.0  # seconds between heartbeats, both ways
HEARTBEAT_LIVENESS = 3  # silent intervals before a client counts as dead
CLIENT_TIMEOUT = 10.0  # seconds a chain (or hop) may take on a client at most (see DEADLINE_FACTOR)
# A chain's deadline: this many times the median measured solve of its kind. Honest solves of one
# kind differ by the machine and the limb; a few times the median keeps a slower machine's work.
DEADLINE_FACTOR = 4.0
DEADLINE_FLOOR = 0.5  # seconds: a deadline no shorter, whatever the median (scheduling, network)
SOLVE_TIMES_KEPT = 64  # measured solves per kind of job, the most recent; their median sets the deadline
# A round stays on the server where its jobs, ceil(jobs / threads) one after another on the
# server's own threads, take less than one job plus this many median hand-overs (a result's
# round trip less the client's solve), each job at its kind's median CPU seconds. On 2 cores
# shared with 4 clients (`python -m server.bench_cluster`, docs/accuracy.md): polishing rounds
# of 4 limb solves of about 3 ms stay against 4-6 ms hand-overs; 4 re-detections of 14 ms and
# 5 whole fits of 30 ms go out.
SHORT_JOB_FACTOR = 1.0
RECEIVE_HWM = 100  # messages queued per peer at most; a client sends a few between the server's reads
MAX_SLEEP = 1.0  # seconds the broker sleeps at most; it wakes for messages, commands and deadlines
SHUTDOWN_GRACE = 1.0  # seconds to wait for clients to acknowledge SHUTDOWN
AUTH_EVENTS = {zmq.EVENT_HANDSHAKE_FAILED_AUTH: "unauthenticated",
               zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL: "handshake",
               zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL: "handshake"}

log = logging.getLogger("server.cluster")


# ----------------------------------------------------------------------------- state

@dataclass
class _ClientStats:
    """Per client name, over all its connections."""

    chains: int = 0
    compute_seconds: float = 0.0   # wall seconds of its chain solves, as it reports them
    cpu_seconds: float = 0.0
    transfer_seconds: float = 0.0  # round trip minus the solve: network, codec, queueing
    bytes_sent: int = 0            # server -> client
    bytes_received: int = 0
    first_seen: float = 0.0
    last_seen: float = 0.0
    late_results: int = 0
    stalls: int = 0
    accepted: int = 0              # results that passed the check and were used or still needed
    rejected: int = 0              # results refused by the check


@dataclass
class _Peer:
    identity: bytes
    client_id: str
    expiry: float
    request: int | None = None     # the one request it works on
    stalled: bool = False          # its request timed out; no work until it answers
    retired: bool = False          # it failed a request: never given work again this session
    frame_sent: tuple | None = None  # the FRAME it holds: (frame number, its masks' digest)


@dataclass
class _Request:
    identity: bytes
    chain: str
    sent: float
    kind: tuple                    # its kind of job (``_job_kind``): whose solve times set its deadline
    timed_out: bool = False


@dataclass
class _Claim:
    """A client's result for a chain, not yet checked."""

    result: ChainResult
    identity: bytes
    client_id: str
    seconds: float                 # its round trip
    kind: tuple
    handover: float                # the round trip less the client's solve
    cpu: float                     # the CPU seconds it reports, at most its solve's and round trip's


@dataclass
class _Round:
    """One dispatch: the limb chains of one iteration of one frame, a round of hops, a frame's
    evolutions or a round of whole fits (the "chains" are then jobs of common.fitting.HOP_JOBS,
    EVOLVE_JOBS or common.search.FIT_JOBS),
    each job with its own start and options."""

    frame: int
    iteration: int
    chains: list
    starts: dict                                         # chain -> (35,) its start
    options: dict                                        # chain -> FitOptions
    wire_options: dict                                   # chain -> options.solve_settings()
    results: dict = field(default_factory=dict)         # chain -> ChainResult, the first checked
    claims: dict = field(default_factory=dict)          # chain -> _Claim, the first to arrive, unchecked
    pending: deque = field(default_factory=deque)        # chains nobody works on
    resent: set = field(default_factory=set)             # of those, the ones queued again
    local: set = field(default_factory=set)              # chains the server is solving
    requests: dict = field(default_factory=dict)         # request id -> _Request
    dispatched: bool = False                             # the broker has handed out what it could
    posted: float = 0.0                                  # perf_counter seconds when the caller asked for it

    def done(self) -> bool:
        return all(c in self.results for c in self.chains)

    def active(self, chain: str) -> bool:
        """Someone is still expected to deliver ``chain``."""
        return (chain in self.results or chain in self.claims or chain in self.pending or chain in self.local
                or any(r.chain == chain and not r.timed_out for r in self.requests.values()))

    def kind(self, chain: str) -> tuple:
        return _job_kind(chain, self.iteration, self.options[chain], self.wire_options[chain])


def _job_kind(chain: str, iteration: int, options: FitOptions, wire_options: dict) -> tuple:
    """Jobs whose solves take alike: whole fits, hops, limb solves that search the limb's whole
    range, other limb solves; each under its options (a first frame's wide search takes longer)."""
    if chain in FIT_JOBS:
        kind = "fit"
    elif chain in HOP_JOBS:
        kind = "hop"
    elif chain in EVOLVE_JOBS:
        kind = "evolve"
    elif iteration == REDETECT_ROUND or (options.redetect_limbs and redetects(options.redetect_turn, chain, iteration)):
        kind = "search"
    else:
        kind = "limb"
    return kind, tuple(sorted(wire_options.items()))


def _chain_result(msg: Result) -> ChainResult:
    return ChainResult(msg.chain, np.asarray(msg.params, dtype=np.float64), whole_energy(msg.energy_before),
                       whole_energy(msg.energy), msg.evaluations, msg.iterations, msg.wall_seconds, msg.cpu_seconds)


# ----------------------------------------------------------------------------- solver

class ClusterSolver:
    """Solver over a ROUTER socket; see the module docstring. ``endpoint`` is the bound address."""

    mode = "cluster"

    def __init__(self, options: FitOptions, bind: str | None = None,
                 heartbeat_interval: float = HEARTBEAT_INTERVAL, client_timeout: float = CLIENT_TIMEOUT,
                 curve_keys: Path | None = None, insecure: bool = False, threads: int = 0):
        """``threads``: the server's own, for the rounds it keeps (``resolve_threads``: 0 is
        $MOCAP_THREADS or every usable core; one keeps none)."""
        bind = default_bind(curve_keys) if bind is None else bind
        if check_bind(bind, curve_keys, insecure):
            log.warning("INSECURE: %s bound without CURVE: any host that reaches it can join and send results",
                        bind)
        if not 0.001 <= heartbeat_interval <= 3600.0:
            raise UserError(f"--heartbeat must be in [0.001, 3600] seconds, got {heartbeat_interval}")
        if not client_timeout > 0:
            raise UserError(f"--client-timeout must be > 0 seconds, got {client_timeout}")
        self.heartbeat_interval, self.client_timeout = heartbeat_interval, client_timeout
        self.session = secrets.token_hex(8)
        self._frame_options = options  # each frame's own, from begin_frame
        self._lock = threading.Condition()
        self._commands: queue.Queue = queue.Queue()
        self._peers: dict[bytes, _Peer] = {}
        self._idle: list[bytes] = []  # least recently busy first
        self._round: _Round | None = None
        self._frame: tuple[tuple, list] | None = None  # ((frame, its masks' digest), encoded FRAME)
        self._next_request = 0
        self._clients_seen: set = set()
        self._banned: set = set()  # client ids that sent a result that failed its check
        self._stats: dict[str, _ClientStats] = {}
        self._solve_times: dict[tuple, deque] = defaultdict(lambda: deque(maxlen=SOLVE_TIMES_KEPT))
        self._deadlines: dict[tuple, float] = {}  # kind of job -> seconds, from _solve_times
        self._measuring: set = set()  # kinds of job the server has taken one of to measure (_unmeasured_job)
        self._backed_up: set = set()  # (session, frame, iteration, request) the server also solved
        self._counts = {"dropped": {}, "rejected": 0, "stalls": 0, "lost_clients": 0, "resent": 0,
                        "local_chains": 0, "backup_chains": 0, "disconnects": 0}
        # seconds: the caller's thread waiting for results, and encoding FRAMEs; the broker's I/O
        self._server = {"waiting_seconds": 0.0, "encode_seconds": 0.0, "io_seconds": 0.0,
                        "local_compute_seconds": 0.0, "check_seconds": 0.0}
        # where a run's wall time goes: rounds (asked for to all results checked) against their
        # jobs' CPU seconds, and the server alone between one round's end and the next's start
        # (torso, head, proposals; a new frame's masks)
        self._rounds = {"rounds": 0, "jobs": 0, "round_seconds": 0.0, "round_job_cpu_seconds": 0.0,
                        "between_rounds_seconds": 0.0, "short_rounds": 0, "short_jobs": 0,
                        "short_round_seconds": 0.0}
        self._job_cpu: dict[tuple, deque] = defaultdict(lambda: deque(maxlen=SOLVE_TIMES_KEPT))  # kind -> s
        self._handovers: deque = deque(maxlen=SOLVE_TIMES_KEPT)  # seconds, round trip less the solve
        self._threads = resolve_threads(threads, options)  # one where the energy is bound to a GL context
        self._pool: HelpingPool | None = None  # made once the socket is bound
        self._here = None  # the frame's dispatch on the server's own cores (common.search.solve_locally)
        self._last_round_end: float | None = None
        self._start_wall = self._start_cpu = None
        self._data: FrameData | None = None
        self._current_frame = 0
        self._closed = False

        self.ctx = zmq.Context()
        self._auth = None
        try:
            self.sock = self.ctx.socket(zmq.ROUTER)
            self.sock.linger = 0
            self.sock.setsockopt(zmq.MAXMSGSIZE, MAX_CLIENT_MESSAGE_BYTES)
            self.sock.rcvhwm = RECEIVE_HWM
            if curve_keys is not None:
                public, secret, allowed = server_keys(curve_keys)
                self._auth = ThreadAuthenticator(self.ctx, log=logging.getLogger("server.cluster.auth"))
                self._auth.start()
                self._auth.configure_curve(domain="*", location=str(allowed))
                self.sock.curve_server = True
                self.sock.curve_publickey, self.sock.curve_secretkey = public, secret
            self.monitor = self.sock.get_monitor_socket(
                zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_FAILED_AUTH
                | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL)
            self.monitor.linger = 0
            try:
                self.sock.bind(bind)
            except zmq.ZMQError as exc:
                raise UserError(f"--bind {bind}: {exc}") from None
            self.endpoint = self.sock.last_endpoint.decode()
            wake = f"inproc://cluster-wake-{self.session}"
            self._wake_rx = self.ctx.socket(zmq.PAIR)
            self._wake_rx.linger = 0
            self._wake_rx.bind(wake)
            self._wake_tx = self.ctx.socket(zmq.PAIR)
            self._wake_tx.linger = 0
            self._wake_tx.connect(wake)
        except BaseException:
            self._teardown()
            raise
        if self._threads > 1:
            self._pool = HelpingPool(self._threads, "cluster-server")
        self._thread = threading.Thread(target=self._broker, name="cluster-broker", daemon=True)
        self._thread.start()
        log.info("listening on %s, session %s", self.endpoint, self.session)

    # ------------------------------------------------------------------ Solver protocol

    @property
    def clients(self) -> int:
        """The clients that delivered accepted work during the run."""
        with self._lock:
            return sum(s.accepted > 0 for s in self._stats.values())

    def client_count(self) -> int:
        with self._lock:
            return len(self._peers)

    def wait_for_clients(self, n: int, timeout: float | None = None, check: Callable[[], None] | None = None) -> int:
        """Block until ``n`` clients are registered (``check()`` may raise meanwhile); returns the count."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while len(self._peers) < n:
                if deadline is not None and time.monotonic() > deadline:
                    raise UserError(f"only {len(self._peers)} of {n} clients registered within {timeout:.0f} s")
                if check:
                    check()
                self._lock.wait(0.2)
            return len(self._peers)

    def workers(self) -> int:
        """The clients that take work now (not stalled, not retired), and the server, which
        solves what no client is free for."""
        with self._lock:
            return 1 + sum(not p.stalled and not p.retired for p in self._peers.values())

    def begin_frame(self, frame: int, data: FrameData, start: np.ndarray, options: FitOptions) -> None:
        t0 = time.perf_counter()
        if self._start_wall is None:
            self._start_wall, self._start_cpu = t0, time.process_time()
        self._data, self._current_frame = data, int(frame)
        self._frame_options = options
        self._here = solve_locally(data.model, data, options, int(frame), self._pool)
        silhouettes = packbits_masks(data.masks)
        msg = Frame(session=self.session, frame=int(frame), cameras=camera_specs(data.studio),
                    silhouettes=silhouettes, previous_params=np.asarray(start).tolist(),
                    body_scale=data.model.scale, body_fingerprint=data.model.fingerprint)
        parts = encode(msg)
        with self._lock:
            self._server["encode_seconds"] += time.perf_counter() - t0
        # a frame is sent again where its masks changed (foreground cleared once the take is fitted)
        self._post(("frame", (int(frame), hashlib.blake2b(silhouettes, digest_size=16).digest()), parts))

    def solve(self, chains: list, params, iteration: int, options=None) -> Callable[[], list]:
        chains = list(chains)
        opts = job_options(options, self._frame_options, len(chains))
        rnd = _Round(self._current_frame, int(iteration), chains, dict(zip(chains, job_starts(params, len(chains)))),
                     dict(zip(chains, opts)), {c: o.solve_settings() for c, o in zip(chains, opts)})
        with self._lock:
            short = self._short([rnd.kind(c) for c in chains])
        if short:
            return self._solve_short(rnd, params, options)
        rnd.pending.extend(rnd.chains)
        with self._lock:
            rnd.posted = time.perf_counter()
            if self._last_round_end is not None:
                self._rounds["between_rounds_seconds"] += rnd.posted - self._last_round_end
            self._round = rnd
        self._post(("round", rnd))
        return lambda: self._collect(rnd)

    def _short(self, kinds: list) -> bool:
        """Whether a round of jobs of ``kinds`` (one per job) is solved sooner on the server's
        threads than by the clients (SHORT_JOB_FACTOR; measured; the lock held)."""
        if self._pool is None or not self._handovers or not all(self._job_cpu[k] for k in kinds):
            return False
        job = max(float(np.median(self._job_cpu[k])) for k in set(kinds))
        here = -(-len(kinds) // self._threads) * job
        return here < job + SHORT_JOB_FACTOR * float(np.median(self._handovers))

    def _solve_short(self, rnd: _Round, params, options) -> Callable[[], list]:
        """``rnd``'s jobs solved on the server's own cores, none sent (the same results)."""
        t0 = time.perf_counter()
        collect = self._here(rnd.chains, params, rnd.iteration, options)

        def collected() -> list:
            results = collect()
            with self._lock:
                self._rounds["short_rounds"] += 1
                self._rounds["short_jobs"] += len(results)
                self._rounds["short_round_seconds"] += time.perf_counter() - t0
                for chain, result in zip(rnd.chains, results):
                    self._job_cpu[rnd.kind(chain)].append(result.cpu_seconds)
            return results

        return collected

    def timing(self) -> dict:
        """Per-process compute / waiting / transfer seconds; the server's rounds (how many, their
        jobs, their wall seconds and their jobs' CPU seconds), its seconds alone between them and
        the rounds it kept (short_rounds, short_jobs, short_round_seconds); and the drop and
        failure counters."""
        with self._lock:
            now = time.perf_counter()
            wall = now - self._start_wall if self._start_wall is not None else 0.0
            srv = self._server
            processes = [{
                "name": "server", "role": "server",
                # the broker's I/O runs beside the caller's thread, mostly while it waits
                "compute_seconds": max(wall - srv["waiting_seconds"] - srv["encode_seconds"], 0.0),
                "waiting_seconds": srv["waiting_seconds"],
                "transfer_seconds": srv["encode_seconds"] + srv["io_seconds"],
                "cpu_seconds": time.process_time() - self._start_cpu if self._start_cpu is not None else 0.0,
                "chains": self._counts["local_chains"],
                "local_compute_seconds": srv["local_compute_seconds"],
                "check_seconds": srv["check_seconds"],  # scoring the clients' results
                **self._rounds,
            }]
            for name, s in sorted(self._stats.items()):
                span = max(s.last_seen - s.first_seen, 0.0)
                processes.append({
                    "name": name, "role": "client", "chains": s.chains,
                    "compute_seconds": s.compute_seconds, "cpu_seconds": s.cpu_seconds,
                    "transfer_seconds": s.transfer_seconds,
                    "waiting_seconds": max(span - s.compute_seconds - s.transfer_seconds, 0.0),
                    "bytes_sent": s.bytes_sent, "bytes_received": s.bytes_received,
                    "late_results": s.late_results, "stalls": s.stalls,
                    "accepted": s.accepted, "rejected": s.rejected,
                })
            return {"processes": processes, "session": self.session, "endpoint": self.endpoint,
                    "clients_seen": len(self._clients_seen), **self._copy_counts()}

    def deadlines(self) -> list[float]:
        """Seconds a chain may take on a client now, one per kind of job with measured solves."""
        with self._lock:
            return sorted(self._deadlines.values())

    def stats(self) -> dict:
        """The counters alone: dropped (by reason), rejected, stalls, lost_clients, resent, local_chains, ..."""
        with self._lock:
            return self._copy_counts()

    def close(self, shutdown: str | None = None) -> None:
        """Stop serving. With ``shutdown``, tell the clients to exit first (end of the run);
        without, they keep trying to reconnect (a server that stops to be restarted)."""
        if self._closed:
            return
        self._closed = True
        if shutdown is not None and self._thread.is_alive():
            self._post(("shutdown", shutdown))
            deadline = time.monotonic() + SHUTDOWN_GRACE
            with self._lock:
                while self._peers and time.monotonic() < deadline:
                    self._lock.wait(0.05)
        self._post(("stop",))
        self._thread.join(timeout=5.0)
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        self._teardown()

    # ------------------------------------------------------------------ caller's thread

    def _post(self, command: tuple) -> None:
        self._commands.put(command)
        try:
            self._wake_tx.send(b"", zmq.NOBLOCK)
        except zmq.Again:  # pokes enough are queued to wake it
            pass

    def _collect(self, rnd: _Round) -> list:
        """Wait for ``rnd``'s chains; check each client's result as it comes; solve locally
        those nobody else can take right now."""
        while True:
            with self._lock:
                t0 = time.perf_counter()
                unmeasured = None
                while not rnd.claims and not rnd.done() and not (rnd.dispatched and rnd.pending):
                    if not self._thread.is_alive():
                        raise RuntimeError("the cluster broker thread died")
                    unmeasured, wait = self._unmeasured_job(rnd) if rnd.dispatched else (None, MAX_SLEEP)
                    if unmeasured is not None:
                        break
                    self._lock.wait(wait)
                self._server["waiting_seconds"] += time.perf_counter() - t0
                if rnd.claims:
                    chain = next(iter(rnd.claims))
                    claim = rnd.claims.pop(chain)
                elif rnd.done():
                    if self._round is rnd:
                        self._round = None
                    self._round_done(rnd)
                    return [rnd.results[c] for c in rnd.chains]
                elif unmeasured is not None:
                    chain, claim = unmeasured, None
                    rnd.local.add(chain)
                else:
                    chain, claim = rnd.pending.popleft(), None
                    rnd.resent.discard(chain)
                    rnd.local.add(chain)
            if claim is not None:
                self._check(rnd, chain, claim)
                continue
            t0 = time.perf_counter()
            result = solve_job(self._data.model, self._data, chain, rnd.starts[chain], rnd.options[chain], rnd.iteration,
                               rnd.frame)
            seconds = time.perf_counter() - t0
            with self._lock:
                self._server["local_compute_seconds"] += seconds
                self._counts["local_chains"] += 1
                self._measured(rnd.kind(chain), seconds)
                self._job_cpu[rnd.kind(chain)].append(result.cpu_seconds)
                rnd.local.discard(chain)
                rnd.results.setdefault(chain, result)
                self._lock.notify_all()

    def _round_done(self, rnd: _Round) -> None:
        """Count ``rnd``, all of whose results are in and checked (the lock held)."""
        self._last_round_end = time.perf_counter()
        totals = self._rounds
        totals["rounds"] += 1
        totals["jobs"] += len(rnd.chains)
        totals["round_seconds"] += self._last_round_end - rnd.posted
        totals["round_job_cpu_seconds"] += sum(rnd.results[c].cpu_seconds for c in rnd.chains)

    def _unmeasured_job(self, rnd: _Round) -> tuple[str | None, float]:
        """(a chain out with a client for ``DEADLINE_FLOOR`` whose kind of job has no measured
        solve yet, seconds to wait before looking again). Its deadline would be the whole
        ``client_timeout``; the server solves it itself instead of waiting (a backup task), which
        measures the kind: peers that never answer cost a measured deadline, not a
        ``client_timeout`` per kind of job. Once per kind, so honest clusters lose little."""
        if rnd.local:
            return None, MAX_SLEEP
        now, wait = time.monotonic(), MAX_SLEEP
        for request, req in rnd.requests.items():
            if (req.timed_out or req.chain in rnd.results or req.chain in rnd.claims
                    or req.kind in self._deadlines or req.kind in self._measuring):
                continue
            age = now - req.sent
            if age >= DEADLINE_FLOOR:
                self._measuring.add(req.kind)
                self._backed_up.add((self.session, rnd.frame, rnd.iteration, request))
                self._counts["backup_chains"] += 1
                return req.chain, 0.0
            wait = min(wait, DEADLINE_FLOOR - age)
        return None, wait

    def _check(self, rnd: _Round, chain: str, claim: _Claim) -> None:
        """Use ``claim`` if its energies are its parameters' (``check_result``); else refuse it,
        queue its chain again and give its sender no more work."""
        t0 = time.perf_counter()
        problem = check_result(self._data, claim.result, rnd.starts[chain], rnd.options[chain], rnd.iteration)
        with self._lock:
            self._server["check_seconds"] += time.perf_counter() - t0
            stats = self._stats[claim.client_id]
            if problem is None:
                stats.accepted += 1
                self._measured(claim.kind, claim.seconds)
                self._job_cpu[claim.kind].append(claim.cpu)
                self._handovers.append(claim.handover)
                rnd.results.setdefault(chain, claim.result)
            else:
                stats.rejected += 1
                self._counts["rejected"] += 1
                if claim.client_id not in self._banned:
                    log.warning("client %s sent a result for %s of frame %d iteration %d that fails its check "
                                "(%s): refused, and the client gets no more work", claim.client_id, chain,
                                rnd.frame, rnd.iteration, problem)
                self._ban(claim.client_id)
                self._requeue_chain(rnd, chain)
            self._lock.notify_all()
        if problem is not None:
            self._post(("assign",))  # the broker hands the chain out again

    # ------------------------------------------------------------------ broker thread

    def _broker(self) -> None:
        poller = zmq.Poller()
        for s in (self.sock, self._wake_rx, self.monitor):
            poller.register(s, zmq.POLLIN)
        next_heartbeat = time.monotonic() + self.heartbeat_interval
        try:
            while True:
                # sleep until the next deadline: waking up takes the GIL from the torso and head fits
                with self._lock:
                    sleep = self._next_deadline(next_heartbeat) - time.monotonic()
                events = dict(poller.poll(max(sleep, 0.0) * 1000))
                if events.get(self._wake_rx):
                    while self._wake_rx.poll(0):
                        self._wake_rx.recv()
                    if not self._run_commands():
                        return
                if events.get(self.monitor):
                    self._read_monitor()
                if events.get(self.sock):
                    self._read_socket()
                now = time.monotonic()
                with self._lock:
                    self._check_peers(now)
                    self._check_requests(now)
                    self._assign()
                    if now >= next_heartbeat:
                        for ident in list(self._peers):
                            self._send(ident, Heartbeat(session=self.session))
                        next_heartbeat = now + self.heartbeat_interval
                    self._lock.notify_all()
        except Exception:
            log.exception("cluster broker failed")
            raise

    def _next_deadline(self, next_heartbeat: float) -> float:
        deadlines = [next_heartbeat, time.monotonic() + MAX_SLEEP]
        deadlines += [p.expiry for p in self._peers.values()]
        if self._round is not None:
            deadlines += [r.sent + self._deadline(r.kind) for r in self._round.requests.values()
                          if not r.timed_out and r.chain not in self._round.results]
        return min(deadlines)

    def _deadline(self, kind: tuple) -> float:
        """Seconds a job of ``kind`` may take on a client (see DEADLINE_FACTOR)."""
        return self._deadlines.get(kind, self.client_timeout)

    def _measured(self, kind: tuple, seconds: float) -> None:
        times = self._solve_times[kind]
        times.append(seconds)
        self._deadlines[kind] = min(self.client_timeout, max(DEADLINE_FLOOR, DEADLINE_FACTOR * float(np.median(times))))

    def _run_commands(self) -> bool:
        while True:
            try:
                command = self._commands.get_nowait()
            except queue.Empty:
                return True
            with self._lock:
                kind = command[0]
                if kind == "stop":
                    return False
                if kind == "frame":
                    self._frame = (command[1], command[2])
                    for peer in self._peers.values():
                        self._send_frame(peer)
                elif kind == "round":
                    self._assign()
                    command[1].dispatched = True
                elif kind == "assign":
                    self._assign()
                elif kind == "shutdown":
                    for ident in list(self._peers):
                        self._send(ident, Shutdown(reason=command[1], session=self.session))
                self._lock.notify_all()

    def _read_monitor(self) -> None:
        while self.monitor.poll(0):
            try:
                event = recv_monitor_message(self.monitor)["event"]
            except zmq.ZMQError:
                return
            with self._lock:
                if event == zmq.EVENT_DISCONNECTED:
                    self._counts["disconnects"] += 1
                elif event in AUTH_EVENTS:
                    self._drop(AUTH_EVENTS[event], "a peer failed the security handshake", None)

    def _read_socket(self) -> None:
        while True:
            try:
                t0 = time.perf_counter()
                frames = self.sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            ident, body = frames[0], frames[1:]
            try:
                msg = decode(body)
                error = None
            except ProtocolError as exc:
                msg, error = None, exc
            elapsed = time.perf_counter() - t0
            with self._lock:
                self._server["io_seconds"] += elapsed
                if error is not None:
                    self._drop(error.reason, error.text, ident)
                    if len(body) > MAX_PARTS and ident in self._peers:  # no client sends that: a flood
                        self._ban(self._peers[ident].client_id)
                        self._forget(ident, "sent a message of more frames than any")
                else:
                    self._handle(ident, msg, sum(len(f) for f in body))
                    self._assign()  # before the caller's thread could take a freed chain itself
                self._lock.notify_all()

    def _send(self, ident: bytes, msg) -> None:
        t0 = time.perf_counter()
        self._send_parts(ident, encode(msg))
        self._server["io_seconds"] += time.perf_counter() - t0

    def _send_parts(self, ident: bytes, parts: list) -> None:
        try:
            self.sock.send_multipart([ident, *parts], zmq.NOBLOCK)
        except zmq.Again:  # the peer's queue is full: it is not reading, and liveness will tell
            pass
        peer = self._peers.get(ident)
        if peer is not None:
            self._stats[peer.client_id].bytes_sent += sum(len(p) for p in parts)

    def _send_frame(self, peer: _Peer) -> None:
        if self._frame is None or peer.frame_sent == self._frame[0]:
            return
        t0 = time.perf_counter()
        self._send_parts(peer.identity, self._frame[1])
        self._server["io_seconds"] += time.perf_counter() - t0
        peer.frame_sent = self._frame[0]

    def _drop(self, reason: str, text: str, ident: bytes | None) -> None:
        dropped = self._counts["dropped"]
        dropped[reason] = dropped.get(reason, 0) + 1
        if dropped[reason] == 1:
            peer = self._peers.get(ident) if ident is not None else None
            who = peer.client_id if peer else (ident.hex() if ident else "a peer")
            log.warning("dropped a message from %s (%s): %s; further drops of this kind are only counted",
                        who, reason, text)

    def _copy_counts(self) -> dict:
        return {k: dict(v) if isinstance(v, dict) else v for k, v in self._counts.items()}

    # ------------------------------------------------------------------ messages (lock held)

    def _handle(self, ident: bytes, msg, size: int) -> None:
        now = time.monotonic()
        peer = self._peers.get(ident)
        if isinstance(msg, Register):
            self._register(ident, msg, now)
            return
        if peer is None:
            self._drop("unregistered", f"{msg.TYPE} from a peer that has not registered", ident)
            self._send(ident, Error(code="unregistered", text="register first", session=self.session))
            return
        peer.expiry = now + HEARTBEAT_LIVENESS * self.heartbeat_interval
        stats = self._stats[peer.client_id]
        stats.bytes_received += size
        stats.last_seen = time.perf_counter()
        if isinstance(msg, Heartbeat):
            return
        if isinstance(msg, Result):
            self._on_result(peer, msg)
        elif isinstance(msg, Error):
            self._on_error(peer, msg)
        else:
            self._drop("unexpected", f"{msg.TYPE} is not sent to the server", ident)

    def _register(self, ident: bytes, msg: Register, now: float) -> None:
        if ident in self._peers:
            self._forget(ident, "registered again")
        elif any(p.client_id == msg.client_id for p in self._peers.values()):
            # a client that reconnected before its old connection timed out, or two clients given
            # one --id: the figures are kept per id, and a refused result stops every connection of it
            log.warning("client %s registered from a second connection while the first is connected: if two "
                        "clients share this --id, their figures are counted as one and a ban stops both",
                        msg.client_id)
        self._peers[ident] = _Peer(ident, msg.client_id, now + HEARTBEAT_LIVENESS * self.heartbeat_interval)
        stats = self._stats.setdefault(msg.client_id, _ClientStats(first_seen=time.perf_counter()))
        stats.last_seen = time.perf_counter()
        self._clients_seen.add(msg.client_id)
        if msg.client_id in self._banned:  # under a new connection: still no work
            self._peers[ident].retired = True
        else:
            self._idle.append(ident)
        self._send(ident, Welcome(session=self.session, heartbeat_interval=self.heartbeat_interval))
        self._send_frame(self._peers[ident])
        log.info("client %s registered (%d connected)", msg.client_id, len(self._peers))

    def _on_result(self, peer: _Peer, msg: Result) -> None:
        rnd = self._round
        req = rnd.requests.get(msg.request) if rnd is not None else None
        stats = self._stats[peer.client_id]
        if peer.client_id in self._banned:
            self._drop("banned", f"result from {peer.client_id}, whose results are refused", peer.identity)
            return
        if msg.request == peer.request or (req is not None and req.identity == peer.identity):
            stats.chains += 1  # work it was asked to do, whether or not the result is still needed
            stats.compute_seconds += msg.wall_seconds
            stats.cpu_seconds += msg.cpu_seconds
        if msg.request == peer.request:
            self._release(peer)
        if (msg.session, msg.frame, msg.iteration, msg.request) in self._backed_up:
            return  # the server solved it too, to measure its kind; whichever came first is used
        if (rnd is None or req is None or msg.session != self.session or msg.frame != rnd.frame
                or msg.iteration != rnd.iteration):
            self._drop("stale", f"result for frame {msg.frame} iteration {msg.iteration} request "
                                f"{msg.request}, not the current round", peer.identity)
            stats.late_results += 1
            return
        if req.identity != peer.identity or req.chain != msg.chain:
            self._drop("mismatch", f"result for {msg.chain} of request {msg.request}, which asked "
                                   f"{req.chain} of another client" if req.identity != peer.identity
                                   else f"result for {msg.chain}, request {msg.request} asked {req.chain}",
                       peer.identity)
            return
        seconds = time.monotonic() - req.sent
        handover = max(seconds - msg.wall_seconds, 0.0)
        stats.transfer_seconds += handover
        cpu = min(msg.cpu_seconds, msg.wall_seconds, seconds)  # what it says decides only where jobs run
        if msg.chain in rnd.results or msg.chain in rnd.claims:
            self._drop("duplicate", f"{msg.chain} of frame {msg.frame} arrived twice", peer.identity)
            return
        rnd.claims[msg.chain] = _Claim(_chain_result(msg), peer.identity, peer.client_id, seconds, req.kind, handover,
                                       cpu)
        if msg.chain in rnd.pending:
            rnd.pending.remove(msg.chain)
            rnd.resent.discard(msg.chain)

    def _on_error(self, peer: _Peer, msg: Error) -> None:
        if msg.code == "client_exit":
            log.info("client %s left: %s", peer.client_id, msg.text)
            self._forget(peer.identity, "left")
            return
        if msg.code == "no_frame":
            peer.frame_sent = None
        else:
            log.warning("client %s failed request %d (%s: %s); it gets no more work", peer.client_id,
                        msg.request, msg.code, msg.text)
            peer.retired = True
        if msg.request == peer.request:
            self._requeue(peer.request)
            self._release(peer)

    def _release(self, peer: _Peer) -> None:
        """``peer`` is done with its request; it may take more unless it failed one."""
        peer.request = None
        peer.stalled = False
        if not peer.retired and peer.identity not in self._idle:
            self._idle.append(peer.identity)

    def _forget(self, ident: bytes, why: str) -> None:
        peer = self._peers.pop(ident)
        if ident in self._idle:
            self._idle.remove(ident)
        if peer.request is not None:
            self._requeue(peer.request)
        log.debug("client %s %s", peer.client_id, why)

    def _requeue(self, request: int) -> None:
        """Queue the chain of ``request`` again unless someone else will still deliver it."""
        rnd = self._round
        req = rnd.requests.get(request) if rnd is not None else None
        if req is None:
            return
        req.timed_out = True
        self._requeue_chain(rnd, req.chain)

    def _requeue_chain(self, rnd: _Round, chain: str) -> None:
        if not rnd.active(chain):
            rnd.pending.appendleft(chain)
            rnd.resent.add(chain)
            self._counts["resent"] += 1

    def _ban(self, client_id: str) -> None:
        """No more work for ``client_id``, under any connection; its current requests go back."""
        self._banned.add(client_id)
        for peer in self._peers.values():
            if peer.client_id == client_id:
                peer.retired = True
                if peer.identity in self._idle:
                    self._idle.remove(peer.identity)
                if peer.request is not None:
                    self._requeue(peer.request)

    def _check_peers(self, now: float) -> None:
        for ident, peer in list(self._peers.items()):
            if now > peer.expiry:
                log.warning("client %s silent for %.1f s: dropped", peer.client_id,
                            HEARTBEAT_LIVENESS * self.heartbeat_interval)
                self._counts["lost_clients"] += 1
                self._forget(ident, "lost")

    def _check_requests(self, now: float) -> None:
        rnd = self._round
        if rnd is None:
            return
        for request, req in rnd.requests.items():
            if (req.timed_out or req.chain in rnd.results or req.chain in rnd.claims
                    or now - req.sent <= self._deadline(req.kind)):
                continue
            peer = self._peers.get(req.identity)
            if peer is not None:
                log.warning("client %s stalled on %s (%.1f s): chain re-sent", peer.client_id, req.chain,
                            now - req.sent)
                peer.stalled = True
                self._stats[peer.client_id].stalls += 1
            self._counts["stalls"] += 1
            self._requeue(request)

    def _assign(self) -> None:
        """Hand queued chains (or hops) to idle clients, longest idle first; a chain queued
        again only to a client that has delivered accepted work (else the server solves it)."""
        rnd = self._round
        if rnd is None:
            return
        for chain in list(rnd.pending):
            proven = [i for i in self._idle if self._stats[self._peers[i].client_id].accepted]
            candidates = proven if chain in rnd.resent else self._idle
            if not candidates:
                if not self._idle:
                    return
                continue
            ident = candidates[0]
            self._idle.remove(ident)
            rnd.pending.remove(chain)
            rnd.resent.discard(chain)
            peer = self._peers[ident]
            request = self._next_request
            self._next_request += 1
            self._send_frame(peer)
            sent = time.monotonic()  # before the message: its round trip includes sending it
            self._send(ident, Solve(session=self.session, frame=rnd.frame, iteration=rnd.iteration,
                                    request=request, params=rnd.starts[chain].tolist(), chains=(chain,),
                                    options=rnd.wire_options[chain]))
            peer.request = request
            rnd.requests[request] = _Request(ident, chain, sent, rnd.kind(chain))

    def _teardown(self) -> None:
        for name in ("_wake_tx", "_wake_rx", "monitor", "sock"):
            s = getattr(self, name, None)
            if s is not None:
                s.close(linger=0)
        if self._auth is not None:
            self._auth.stop()
        self.ctx.term()
