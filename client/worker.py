"""The limb worker: a DEALER that registers with the server and solves the chains it is sent
(and hops and whole fits, ``common.search.solve_job``).

Flow (one connection)::

    client                                server
    REGISTER(client_id, cores, backends) ──►
                                          ◄── WELCOME(session, heartbeat_interval)
                                          ◄── FRAME(session, frame, cameras, silhouettes)  once per frame
                                          ◄── SOLVE(session, frame, iteration, request, params, chains)
    RESULT(..., chain, params, energy) ──►    one per chain, as each finishes
    HEARTBEAT(session) ◄─────────────────►    both ways, every interval
                                          ◄── SHUTDOWN                   the run is over: exit

Reliability follows zguide's Paranoid Pirate worker: the server is presumed gone after
``HEARTBEAT_LIVENESS`` intervals of silence, and the worker then closes its socket, waits
(1 s, doubling up to 32 s) and connects afresh with a new REGISTER. A server that does not
know us (it restarted) answers anything but REGISTER with ERROR "unregistered", and we register
again at once. Chains are solved on a compute thread so that heartbeats keep flowing during a
long solve; only the main thread touches the DEALER. Results of a session that is no longer
current are dropped, never sent.

Every message from the wire goes through ``common.protocol.decode``; bad ones are logged once
per reason, counted (``Worker.dropped``) and dropped.

A server that refuses our CURVE handshake (our key is not in its allow-list, or we hold the
wrong server key) sends nothing at all; the socket monitor tells us, and after
``HANDSHAKE_REFUSALS`` refused connections with no session between them ``run`` returns
"refused", with that said in one line.
"""
from __future__ import annotations

import logging
import os
import queue
import socket
import threading
import time
from dataclasses import dataclass
import importlib.util
from importlib import metadata

import numpy as np
import zmq
import zmq.auth
from zmq.utils.monitor import recv_monitor_message

from common.body import BodyModel
from common.camera import Studio
from common.fitting import FitOptions, FrameData
from common.search import solve_job
from common.protocol import (
    MAX_MESSAGE_BYTES, Error, Frame, Heartbeat, ProtocolError, Register, Result, Shutdown, Solve, Welcome,
    decode, encode,
)

HEARTBEAT_INTERVAL = 1.0  # seconds, until the server's WELCOME says otherwise
HEARTBEAT_LIVENESS = 3  # silent intervals before the server counts as gone
RECONNECT_MIN = 1.0  # seconds before the first reconnect; doubles after every failed one
RECONNECT_MAX = 32.0  # seconds
MAX_SLEEP = 1.0  # seconds the main loop sleeps at most (it wakes for messages, results and stop())
FRAMES_KEPT = 2  # FRAME messages cached: the current frame and the one received before
HANDSHAKE_REFUSALS = 3  # refused connections before giving up: a key problem, not a glitch
HANDSHAKE_EVENTS = (zmq.EVENT_HANDSHAKE_FAILED_AUTH | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
                    | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL)
REFUSED = ("server refused the CURVE handshake: is this client's key in the server's clients/ folder, "
           "and the server key right? (a server without --curve-keys refuses CURVE clients too)")
REFUSED_NO_KEYS = ("server refused the handshake: it asks for CURVE keys; give this client --curve-keys "
                   "FOLDER (the folder mocap keys made for it)")


def refusal(curve) -> str:
    """Why a handshake failed, as far as a client with (or without) ``curve`` keys can tell."""
    return REFUSED if curve is not None else REFUSED_NO_KEYS

# energy backends this client can try (a failing one is reported as an ERROR, and the server
# then solves those chains itself)
BACKENDS = ("cpu", "gl") if importlib.util.find_spec("moderngl") else ("cpu",)

log = logging.getLogger("client")


def software_version() -> str:
    try:
        return metadata.version("silhouette-mocap")
    except metadata.PackageNotFoundError:  # running from a source tree
        return "0+source"


@dataclass(frozen=True)
class CurveKeys:
    """This client's CURVE key pair and the server's public key (z85 bytes)."""

    public: bytes
    secret: bytes
    server: bytes

    @classmethod
    def load(cls, directory: str) -> "CurveKeys":
        """``DIR/client.key_secret`` (this client) and ``DIR/server.key`` (the server's public key)."""
        for name in ("client.key_secret", "server.key"):
            if not os.path.isfile(os.path.join(directory, name)):  # zmq would say only "Invalid certificate file"
                where = (f"no {name} there" if os.path.isdir(directory)
                         else "a file, not a folder" if os.path.exists(directory) else "no such folder")
                raise ValueError(f"{where}; give the folder mocap keys made for this client (for-NAME/)")
        public, secret = zmq.auth.load_certificate(os.path.join(directory, "client.key_secret"))
        server, _ = zmq.auth.load_certificate(os.path.join(directory, "server.key"))
        if secret is None:
            raise ValueError(f"{directory}/client.key_secret holds no secret key")
        return cls(public, secret, server)


@dataclass(frozen=True)
class _Job:
    session: str
    frame: Frame
    solve: Solve | None  # None: only prepare the frame's data


class Worker:
    """One client. ``run()`` serves until ``stop()``, a SHUTDOWN, or (with ``exit_with_parent``)
    the parent process going away; it returns the reason.

    ``stall_seconds``/``stall_requests`` are for fault tests only: the compute thread sleeps
    that long before each of the first ``stall_requests`` SOLVE requests, while heartbeats go on.
    """

    def __init__(self, model: BodyModel, connect: str, client_id: str | None = None,
                 curve: CurveKeys | None = None, context: zmq.Context | None = None,
                 reconnect_min: float = RECONNECT_MIN, reconnect_max: float = RECONNECT_MAX,
                 exit_with_parent: bool = False, stall_seconds: float = 0.0, stall_requests: int = 0):
        self.model = model  # the body data; each FRAME says the actor's size to fit it at
        self.connect = connect
        # host and pid repeat across containers (own pid spaces, shared host names): add a nonce
        self.client_id = client_id or f"{socket.gethostname()}-{os.getpid()}-{os.urandom(3).hex()}"
        self.curve = curve
        self.reconnect_min, self.reconnect_max = reconnect_min, reconnect_max
        self.parent = os.getppid() if exit_with_parent else None
        self.stall_seconds, self.stall_requests = stall_seconds, stall_requests
        self.ctx = context or zmq.Context()
        self._own_ctx = context is None
        self._stop = threading.Event()
        self.dropped: dict[str, int] = {}
        self.solved = 0
        self._scaled: BodyModel | None = None  # the body at the last FRAME's size, when not the model's
        self.sessions = 0  # how many times a WELCOME was received (1 + re-registrations)
        self._jobs: queue.Queue = queue.Queue()
        self._done: queue.Queue = queue.Queue()
        # the compute thread pokes the main loop through this pair when a result is ready
        wake_addr = f"inproc://client-wake-{id(self)}"
        self._wake_rx = self.ctx.socket(zmq.PAIR)
        self._wake_rx.linger = 0
        self._wake_rx.bind(wake_addr)
        self._wake_tx = self.ctx.socket(zmq.PAIR)
        self._wake_tx.linger = 0
        self._wake_tx.connect(wake_addr)
        self._wake_lock = threading.Lock()
        self._compute = threading.Thread(target=self._compute_loop, name="client-compute", daemon=True)
        self._compute.start()
        # connection state, main thread only
        self.session = ""
        self.heartbeat_interval = HEARTBEAT_INTERVAL
        self._heartbeat_at = 0.0
        self._frames: dict[tuple[str, int], Frame] = {}

    # ------------------------------------------------------------------ public

    def stop(self) -> None:
        """Ask ``run`` to return (thread-safe, and safe in a signal handler)."""
        self._stop.set()
        self._poke(blocking=False)  # in a handler the lock may be held below us: MAX_SLEEP then

    def run(self) -> str:
        backoff = self.reconnect_min
        refusals = 0
        try:
            while True:
                sock, monitor = self._open()
                try:
                    outcome = self._serve(sock, monitor)
                finally:
                    sock.disable_monitor()
                    monitor.close(linger=0)
                    sock.close(linger=0)
                if outcome == "refused":
                    refusals += 1
                elif self.session:  # it let us in: a later refusal starts the count afresh
                    refusals = 0
                if refusals >= HANDSHAKE_REFUSALS:
                    return "refused"
                if outcome not in ("lost", "refused"):
                    return outcome
                if self.session:
                    backoff = self.reconnect_min  # we had a session: a fresh loss, start over
                if outcome == "refused":
                    log.warning("%s Retrying in %.1f s", refusal(self.curve), backoff)
                else:  # never heard from: nothing may be listening there
                    log.warning("server %s silent for %.1f s%s; reconnecting in %.1f s", self.connect,
                                HEARTBEAT_LIVENESS * self.heartbeat_interval,
                                "" if self.sessions else " (no answer yet: is a server running there?)", backoff)
                self.session = ""
                self._frames.clear()
                if self._stop.wait(backoff) or self._parent_gone():
                    return "stopped"
                backoff = min(2 * backoff, self.reconnect_max)
        finally:
            self._jobs.put(None)
            self._wake_rx.close(linger=0)
            with self._wake_lock:
                self._wake_tx.close(linger=0)
            if self._own_ctx:
                self.ctx.term()

    # ------------------------------------------------------------------ connection

    def _open(self) -> tuple[zmq.Socket, zmq.Socket]:
        """A connected DEALER that has sent REGISTER, and its monitor for failed handshakes
        (watching before the connection starts, so that none is missed)."""
        sock = self.ctx.socket(zmq.DEALER)
        monitor = None
        try:
            sock.linger = 0
            sock.setsockopt(zmq.MAXMSGSIZE, MAX_MESSAGE_BYTES)
            if self.curve:
                sock.curve_publickey, sock.curve_secretkey = self.curve.public, self.curve.secret
                sock.curve_serverkey = self.curve.server
            monitor = sock.get_monitor_socket(HANDSHAKE_EVENTS)
            monitor.linger = 0
            sock.connect(self.connect)
        except zmq.ZMQError:
            if monitor is not None:
                sock.disable_monitor()
                monitor.close(linger=0)
            sock.close(linger=0)  # an open socket would keep the context from terminating
            raise
        self._register(sock)
        return sock, monitor

    def _register(self, sock: zmq.Socket) -> None:
        self._send(sock, Register(client_id=self.client_id, cores=os.cpu_count() or 1, backends=BACKENDS,
                                  version=software_version()))

    def _send(self, sock: zmq.Socket, msg) -> None:
        try:
            sock.send_multipart(encode(msg), zmq.NOBLOCK)
        except zmq.Again:  # queue full while the server is away: heartbeats and retries cover it
            pass

    def _serve(self, sock: zmq.Socket, monitor: zmq.Socket) -> str:
        poller = zmq.Poller()
        poller.register(sock, zmq.POLLIN)
        poller.register(self._wake_rx, zmq.POLLIN)
        poller.register(monitor, zmq.POLLIN)
        now = time.monotonic()
        server_expiry = now + HEARTBEAT_LIVENESS * self.heartbeat_interval
        self._heartbeat_at = now + self.heartbeat_interval
        while True:
            if self._stop.is_set() or self._parent_gone():
                self._say_goodbye(sock, "stopped")
                return "stopped"
            # sleep until something happens: a wake-up while the compute thread runs costs it the GIL
            timeout = max(0.0, min(self._heartbeat_at, server_expiry, time.monotonic() + MAX_SLEEP)
                          - time.monotonic())
            events = dict(poller.poll(timeout * 1000))
            if events.get(self._wake_rx):
                while self._wake_rx.poll(0):
                    self._wake_rx.recv()
            if events.get(monitor) and self._refused(monitor):
                return "refused"
            self._send_results(sock)
            if events.get(sock):
                while True:
                    try:
                        frames = sock.recv_multipart(zmq.NOBLOCK, copy=True)
                    except zmq.Again:
                        break
                    outcome = self._handle(sock, frames)
                    if outcome:
                        return outcome
                    server_expiry = time.monotonic() + HEARTBEAT_LIVENESS * self.heartbeat_interval
            now = time.monotonic()
            if now >= self._heartbeat_at:
                self._send(sock, Heartbeat(session=self.session))
                self._heartbeat_at = now + self.heartbeat_interval
            if now >= server_expiry:
                return "lost"

    def _refused(self, monitor: zmq.Socket) -> bool:
        """Whether the monitor reports a failed handshake (it reports nothing else)."""
        refused = False
        while monitor.poll(0):
            recv_monitor_message(monitor)
            refused = True
        return refused

    def _say_goodbye(self, sock: zmq.Socket, why: str) -> None:
        """Tell the server we leave, so it re-sends our chain now instead of after the liveness timeout."""
        if self.session:
            self._send(sock, Error(code="client_exit", text=why, session=self.session))

    def _parent_gone(self) -> bool:
        return self.parent is not None and os.getppid() != self.parent

    # ------------------------------------------------------------------ messages

    def _drop(self, reason: str, text: str) -> None:
        count = self.dropped.get(reason, 0)
        self.dropped[reason] = count + 1
        if count == 0:
            log.warning("dropped a message (%s): %s; further drops of this kind are only counted", reason, text)

    def _handle(self, sock: zmq.Socket, frames: list) -> str | None:
        try:
            msg = decode(frames)
        except ProtocolError as exc:
            self._drop(exc.reason, exc.text)
            return None
        if isinstance(msg, Welcome):
            if msg.session != self.session:
                self._frames.clear()
            self.session, self.heartbeat_interval = msg.session, msg.heartbeat_interval
            self._heartbeat_at = min(self._heartbeat_at, time.monotonic() + msg.heartbeat_interval)
            self.sessions += 1
            log.info("registered with %s, session %s", self.connect, msg.session)
        elif isinstance(msg, Heartbeat):
            pass
        elif isinstance(msg, Shutdown):
            log.info("server says shut down: %s", msg.reason)
            self._say_goodbye(sock, "shutdown")
            return "shutdown"
        elif isinstance(msg, Error):
            if msg.code == "unregistered":  # a restarted server: register again now
                self.session = ""
                self._register(sock)
            else:
                log.warning("server error %s: %s", msg.code, msg.text)
        elif not isinstance(msg, (Frame, Solve)):
            self._drop("unexpected", f"{msg.TYPE} is not sent to clients")
        elif not self.session or msg.session != self.session:
            self._drop("stale", f"{msg.TYPE} for session {msg.session!r}, ours is {self.session!r}")
        elif isinstance(msg, Frame):
            # the most recently received are kept, not the highest numbered: refinement goes backwards
            self._frames.pop((msg.session, msg.frame), None)
            self._frames[(msg.session, msg.frame)] = msg
            self._jobs.put(_Job(msg.session, msg, None))  # unpack it while the server fits the torso
            while len(self._frames) > FRAMES_KEPT:
                del self._frames[next(iter(self._frames))]
        else:
            frame = self._frames.get((msg.session, msg.frame))
            if frame is None:
                self._send(sock, Error(code="no_frame", text=f"no FRAME {msg.frame} received",
                                       session=msg.session, frame=msg.frame, iteration=msg.iteration,
                                       request=msg.request))
            else:
                log.debug("solving frame %d iteration %d request %d: %s", msg.frame, msg.iteration,
                          msg.request, ", ".join(msg.chains))
                self._jobs.put(_Job(msg.session, frame, msg))
        return None

    def _send_results(self, sock: zmq.Socket) -> None:
        while True:
            try:
                msg = self._done.get_nowait()
            except queue.Empty:
                return
            if msg.session == self.session:  # a result for an older server is of no use
                self._send(sock, msg)

    # ------------------------------------------------------------------ compute thread

    def _compute_loop(self) -> None:
        cache: tuple[Frame, FrameData] | None = None  # the FRAME last unpacked: one sent again (its masks changed) is new
        while True:
            job = self._jobs.get()
            if job is None:
                return
            if job.session != self.session:  # the server restarted meanwhile: nobody wants this
                continue
            if job.solve is None:
                try:
                    if cache is None or cache[0] is not job.frame:
                        cache = (job.frame, self._frame_data(job.frame))
                except Exception as exc:  # reported with the first SOLVE that needs it
                    log.warning("cannot use FRAME %d: %s", job.frame.frame, exc)
                continue
            solve = job.solve
            if self.stall_requests > 0:
                self.stall_requests -= 1
                time.sleep(self.stall_seconds)
            try:
                options = FitOptions.from_wire(solve.options)
                if cache is None or cache[0] is not job.frame:
                    cache = (job.frame, self._frame_data(job.frame))
                for chain in solve.chains:
                    r = solve_job(cache[1].model, cache[1], chain, np.asarray(solve.params), options,
                                  solve.iteration, solve.frame)
                    self.solved += 1
                    self._finish(Result(session=solve.session, frame=solve.frame, iteration=solve.iteration,
                                        request=solve.request, chain=r.chain, params=r.params.tolist(),
                                        energy=float(r.energy), energy_before=float(r.energy_before),
                                        evaluations=r.evaluations, iterations=r.iterations,
                                        cpu_seconds=r.cpu_seconds, wall_seconds=r.wall_seconds))
            except Exception as exc:  # whatever fails, the server must hear of it, and we go on
                log.warning("cannot solve request %d: %s", solve.request, exc)
                self._finish(Error(code="solve_failed", text=str(exc)[:1000], session=solve.session,
                                   frame=solve.frame, iteration=solve.iteration, request=solve.request))

    def _frame_data(self, frame: Frame) -> FrameData:
        body = self._body_at(frame.body_scale)
        if frame.body_fingerprint != body.fingerprint:
            raise ValueError(f"the server fits body {frame.body_fingerprint}, this client has body "
                             f"{body.fingerprint} at size {frame.body_scale:g} (different body data)")
        studio = Studio(tuple(c.to_camera() for c in frame.cameras), "<wire>")
        return FrameData(body, studio, frame.masks())

    def _body_at(self, scale: float) -> BodyModel:
        """The body at the actor's size ``scale`` (over the body model's), scaled as the server's
        was (``BodyModel.scaled`` from the model's own size), so that the fingerprints agree."""
        if scale != self.model.scale:
            if self._scaled is None or self._scaled.scale != scale:
                self._scaled = self.model.scaled(scale / self.model.scale)
            return self._scaled
        return self.model

    def _finish(self, msg) -> None:
        self._done.put(msg)
        self._poke()

    def _poke(self, blocking: bool = True) -> None:
        """Wake the main loop from another thread."""
        if not self._wake_lock.acquire(blocking):
            return
        try:
            if not self._wake_tx.closed:
                self._wake_tx.send(b"", zmq.NOBLOCK)
        except zmq.Again:  # it has pokes enough to wake up
            pass
        finally:
            self._wake_lock.release()

