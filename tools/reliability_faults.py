"""Faults injected into small distributed runs, each against an undisturbed single-process fit.

    python tools/reliability_faults.py [--measure-flood]

``run_faults(work_dir)`` returns one dict per case: {"name", "survived", "outcome" (one line),
"seconds"}. Survived: every frame present once with the undisturbed run's poses, or the run
refused with a clear one-line message. The sequence is synthetic (4 cameras at 160x120,
3 frames of the bundled walk, as the tests' small sequence), fitted with tracking only; the
whole set takes about a minute on two cores. ``--measure-flood`` also measures the peak RSS
of a server sent one message of 20 frames of 60 MB, with the old per-frame limit and with
the current one (docs/cluster.md).
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import zmq  # noqa: E402

from common.body import load_body_model  # noqa: E402
from common.fitting import FitOptions  # noqa: E402
from common.protocol import MAX_CLIENT_MESSAGE_BYTES, Heartbeat, Register, Result, Solve, decode, encode  # noqa: E402

FRAMES = 3
CAMERAS, SIZE = 4, (160, 120)  # pixels, width and height
OPTIONS = FitOptions(refine_passes=0)  # tracking only: the passes solve through the same solver
HEARTBEAT = 0.3  # seconds: quick failure detection in small runs
FAKE_BEAT = 0.1  # seconds between a fake peer's heartbeats, well inside the server's liveness
STALL_CLIENT_TIMEOUT = 2.0  # seconds: the deadline until a solve has been measured
STALL_PEERS = 20
# A crowd of silent peers may cost a measured deadline for each round that hands its chains to
# fresh silent peers (the server measures a new kind of job itself rather than wait a client
# timeout on it), with room for a loaded machine: not one timeout per peer (before: 5 timeouts
# in the first round), nor one per kind of job.
STALL_SLACK = 2.0
FLOOD_PARTS, FLOOD_PART_BYTES = 20, 60_000_000  # the flood of the issue: 20 frames of 60 MB
OLD_MAX_FRAME_BYTES = 64 * 1024 * 1024  # the server's per-frame limit before it was the clients' largest
SUBPROCESS_TIMEOUT = 60.0  # seconds for a client or server process of a case
TOLERANCE = 1e-9  # radians and metres: the poses match bit for bit in practice


class FakePeers:
    """``n`` raw DEALERs in one thread that register and heartbeat; ``answer(solve) -> Result``
    makes them answer each SOLVE (None: never). ``solves`` holds the SOLVEs they got."""

    def __init__(self, endpoint: str, n: int, name: str, answer=None):
        self.ctx = zmq.Context()
        self.socks = []
        for i in range(n):
            s = self.ctx.socket(zmq.DEALER)
            s.linger = 0
            s.connect(endpoint)
            s.send_multipart(encode(Register(client_id=f"{name}-{i}", cores=1, backends=("cpu",), version="0")))
            self.socks.append(s)
        self.answer, self.solves, self.session = answer, [], ""
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        poller = zmq.Poller()
        for s in self.socks:
            poller.register(s, zmq.POLLIN)
        next_beat = 0.0
        while not self._done.is_set():
            if time.monotonic() >= next_beat:
                for s in self.socks:
                    s.send_multipart(encode(Heartbeat(session=self.session)), zmq.NOBLOCK)
                next_beat = time.monotonic() + FAKE_BEAT
            for s, _ in poller.poll(20):
                msg = decode(s.recv_multipart())
                self.session = getattr(msg, "session", "") or self.session
                if isinstance(msg, Solve):
                    self.solves.append(msg)
                    if self.answer is not None:
                        s.send_multipart(encode(self.answer(msg)))

    def close(self) -> None:
        self._done.set()
        self._thread.join(5)
        self.ctx.destroy(linger=0)


def random_answers(seed: int = 0):
    """Random parameters claiming energy 0: what a broken or hostile client might send."""
    rng = np.random.default_rng(seed)

    def answer(msg: Solve) -> Result:
        return Result(session=msg.session, frame=msg.frame, iteration=msg.iteration, request=msg.request,
                      chain=msg.chains[0], params=rng.uniform(-1.0, 1.0, 35).tolist(), energy=0.0,
                      energy_before=0.0, evaluations=1, iterations=1, cpu_seconds=0.0, wall_seconds=0.0)
    return answer


class _Context:
    """The sequence, the body model and the undisturbed poses all cases compare against."""

    def __init__(self, work_dir: Path):
        from common.camera import circle_studio
        from common.synth import SynthOptions, synthesize
        from server.session import LocalSolver, run_fit

        self.work_dir = work_dir
        self.model = load_body_model()
        self.sequence = work_dir / "sequence"
        synthesize(self.model, circle_studio(CAMERAS, *SIZE), REPO / "common" / "data" / "clips" / "cmu_12_01_walk.bvh",
                   self.sequence, SynthOptions(frames=FRAMES, start=1, step=4, noise="none", seed=0))
        t0 = time.perf_counter()
        run_fit(self.model, self._load(), work_dir / "undisturbed", OPTIONS, LocalSolver(self.model, OPTIONS))
        self.clean_seconds = time.perf_counter() - t0
        self.reference = poses(work_dir / "undisturbed")

    def _load(self):
        from common.sequence import load_sequence

        return load_sequence(self.sequence)

    def fit(self, solver, name: str) -> tuple[dict, Path]:
        from server.session import run_fit

        out = self.work_dir / name
        return run_fit(self.model, self._load(), out, OPTIONS, solver), out

    def complete(self, out: Path) -> str | None:
        """None when every frame is there once with the undisturbed poses; else what is wrong."""
        records = load_records(out)
        frames = [r["frame"] for r in records]
        if frames != list(range(FRAMES)):
            return f"frames {frames}, expected 0..{FRAMES - 1} once each"
        worst = float(np.abs(np.array([r["params"] for r in records]) - self.reference).max())
        return None if worst <= TOLERANCE else f"poses differ from the undisturbed run by up to {worst:.3g}"

    def solver(self, **kwargs):
        from server.cluster import LOCAL_BIND, ClusterSolver

        return ClusterSolver(OPTIONS, bind=LOCAL_BIND, heartbeat_interval=HEARTBEAT, **kwargs)


def load_records(out: Path) -> list[dict]:
    path = out / "poses.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def poses(out: Path) -> np.ndarray:
    return np.array([r["params"] for r in load_records(out)])


def _env() -> dict:
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def _client(endpoint: str, name: str, log: Path, *extra: str) -> subprocess.Popen:
    with open(log, "w") as fh:
        return subprocess.Popen([sys.executable, "-m", "client", "--connect", endpoint, "--id", name,
                                 "--reconnect-min", "0.2", "--exit-with-parent", *extra],
                                cwd=REPO, env=_env(), stdout=fh, stderr=fh, stdin=subprocess.DEVNULL)


def _stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
        p.wait(10)


def _wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout:g} s")
        time.sleep(0.02)


# ----------------------------------------------------------------------------- cases
# each returns (survived, outcome)

def _fit_beside_one_peer(ctx: _Context, case: str, name: str, answer=None) -> tuple[dict, Path]:
    """A run with one honest client process and one fake peer ``name`` (answering with ``answer``)."""
    solver = ctx.solver()
    peer = FakePeers(solver.endpoint, 1, name, answer)
    good = _client(solver.endpoint, "good", ctx.work_dir / f"{case}-good.log")
    try:
        solver.wait_for_clients(2, SUBPROCESS_TIMEOUT)
        return ctx.fit(solver, case)
    finally:
        peer.close()
        solver.close(shutdown="done")
        _stop([good])


def poisoned_results(ctx: _Context) -> tuple[bool, str]:
    summary, out = _fit_beside_one_peer(ctx, "poisoned", "liar", random_answers())
    problem = ctx.complete(out)
    rejected = summary["timing"]["rejected"]
    liar_accepted = next(p["accepted"] for p in summary["timing"]["processes"] if p["name"] == "liar-0")
    ok = problem is None and rejected >= 1 and liar_accepted == 0 and summary["clients"] == 1
    return ok, (problem or f"{rejected} random results claiming energy 0 refused, the liar got no more work; "
                           f"clients that did work: {summary['clients']}")


def multipart_flood(ctx: _Context) -> tuple[bool, str]:
    solver = ctx.solver()
    good = _client(solver.endpoint, "good", ctx.work_dir / "flood-good.log")
    zctx = zmq.Context()
    try:
        solver.wait_for_clients(1, SUBPROCESS_TIMEOUT)
        flood = zctx.socket(zmq.DEALER)
        flood.linger = 0
        flood.connect(solver.endpoint)
        flood.send_multipart(encode(Register(client_id="flood", cores=1, backends=("cpu",), version="0")))
        _wait_for(lambda: solver.client_count() == 2, 10, "flood peer registered")
        # frames as large as the server takes, more of them than any message has
        flood.send_multipart([encode(Heartbeat())[0]] + [b"\0" * MAX_CLIENT_MESSAGE_BYTES] * FLOOD_PARTS)
        _wait_for(lambda: solver.stats()["dropped"].get("too_large"), 10, "drop of the flood")
        forgotten = solver.client_count() == 1
        # the flood: zmq refuses its first 60 MB frame and closes the connection
        big = zctx.socket(zmq.DEALER)
        big.linger = 0
        big.connect(solver.endpoint)
        part = b"\0" * FLOOD_PART_BYTES
        big.send_multipart([part] * FLOOD_PARTS)
        _wait_for(lambda: solver.stats()["disconnects"] >= 1, 10, "disconnect of the 60 MB frames")
        summary, out = ctx.fit(solver, "flood")
    finally:
        zctx.destroy(linger=0)
        solver.close(shutdown="done")
        _stop([good])
    problem = ctx.complete(out)
    ok = problem is None and forgotten
    return ok, (problem or f"{FLOOD_PARTS}-frame message dropped and its sender forgotten; "
                           f"{FLOOD_PARTS} x 60 MB cut off at the first frame (disconnects "
                           f"{summary['timing']['disconnects']})")


def stalling_peers(ctx: _Context) -> tuple[bool, str]:
    solver = ctx.solver(client_timeout=STALL_CLIENT_TIMEOUT)
    crowd = FakePeers(solver.endpoint, STALL_PEERS, "silent")
    try:
        solver.wait_for_clients(STALL_PEERS, 10)
        t0 = time.perf_counter()
        summary, out = ctx.fit(solver, "stalling")
        seconds = time.perf_counter() - t0
    finally:
        crowd.close()
        solver.close()
    problem = ctx.complete(out)
    from common.body import LIMB_CHAINS
    from server.cluster import DEADLINE_FLOOR

    rounds = -(-STALL_PEERS // len(LIMB_CHAINS))
    deadline = max([DEADLINE_FLOOR, *solver.deadlines()])
    allowed = STALL_SLACK * (ctx.clean_seconds + rounds * deadline)
    ok = problem is None and seconds <= allowed and summary["clients"] == 0
    return ok, (problem or f"{STALL_PEERS} peers that never answer: {seconds:.1f} s against {ctx.clean_seconds:.1f} s "
                           f"undisturbed (allowed {allowed:.1f} s), {summary['timing']['stalls']} stalls")


def fake_client(ctx: _Context) -> tuple[bool, str]:
    summary, out = _fit_beside_one_peer(ctx, "fake", "fake")
    problem = ctx.complete(out)
    ok = problem is None and summary["clients"] == 1
    return ok, (problem or f"a registered client that never works: summary counts {summary['clients']} client "
                           f"(the one that worked), {summary['timing']['stalls']} stall(s)")


def network_bind_without_keys(ctx: _Context) -> tuple[bool, str]:
    proc = subprocess.run([sys.executable, "-m", "server.cli", "server", str(ctx.sequence), "--out",
                           str(ctx.work_dir / "unsafe"), "--bind", "tcp://*:5555"],
                          cwd=REPO, env=_env(), capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT)
    lines = proc.stderr.strip().splitlines()
    ok = proc.returncode == 2 and len(lines) == 1 and "--curve-keys" in lines[0] and "Traceback" not in proc.stderr
    return ok, f"exit {proc.returncode}: {lines[0] if lines else '(nothing said)'}"


def curve_refusal(ctx: _Context) -> tuple[bool, str]:
    from server.trust import create_curve_keys

    keys = create_curve_keys(ctx.work_dir / "keys")
    stranger = create_curve_keys(ctx.work_dir / "stranger")  # a pair the server does not allow
    (stranger / "server.key").write_bytes((keys / "server.key").read_bytes())
    solver = ctx.solver(curve_keys=keys)
    try:
        proc = subprocess.run([sys.executable, "-m", "client", "--connect", solver.endpoint, "--curve-keys",
                               str(stranger), "--reconnect-min", "0.2", "--quiet"],
                              cwd=REPO, env=_env(), capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT)
        admitted = solver.client_count()
    finally:
        solver.close()
    line = proc.stderr.strip().splitlines()[-1:] or ["(nothing said)"]
    ok = proc.returncode != 0 and admitted == 0 and "refused the CURVE handshake" in line[0]
    return ok, f"client exit {proc.returncode}: {line[0]}"


def client_killed(ctx: _Context) -> tuple[bool, str]:
    solver = ctx.solver()
    doomed_log = ctx.work_dir / "killed-doomed.log"
    good = _client(solver.endpoint, "good", ctx.work_dir / "killed-good.log")
    # it holds its first chain long enough to be killed with it
    doomed = _client(solver.endpoint, "doomed", doomed_log, "-v", "--test-stall", "30")
    result = {}

    def run():
        try:
            result["summary"], result["out"] = ctx.fit(solver, "killed")
        except Exception as exc:  # said in the outcome
            result["error"] = exc

    try:
        solver.wait_for_clients(2, SUBPROCESS_TIMEOUT)
        fit = threading.Thread(target=run)
        fit.start()
        _wait_for(lambda: doomed_log.exists() and "solving frame" in doomed_log.read_text(), SUBPROCESS_TIMEOUT,
                  "chain for the doomed client")
        doomed.send_signal(signal.SIGKILL)
        fit.join(SUBPROCESS_TIMEOUT)
    finally:
        solver.close(shutdown="done")
        _stop([good, doomed])
    if "out" not in result:
        return False, f"the run failed: {result.get('error', 'did not finish')}"
    problem = ctx.complete(result["out"])
    timing = result["summary"]["timing"]
    return problem is None, (problem or f"SIGKILL mid-chain: {timing['lost_clients']} client lost, "
                                        f"{timing['resent']} chain(s) re-sent")


CASES = (
    ("poisoned results", poisoned_results),
    ("multi-part flood", multipart_flood),
    ("stalling fake clients", stalling_peers),
    ("fake client that never works", fake_client),
    ("non-loopback bind without keys", network_bind_without_keys),
    ("CURVE refusal", curve_refusal),
    ("client SIGKILLed mid-run", client_killed),
)


def run_faults(work_dir: Path) -> list[dict]:
    """Every case of CASES in ``work_dir`` (made if missing): [{"name", "survived", "outcome", "seconds"}]."""
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    ctx = _Context(work_dir)
    cases = []
    for name, case in CASES:
        t0 = time.perf_counter()
        try:
            survived, outcome = case(ctx)
        except Exception as exc:  # a case that breaks is a fault not survived, said in one line
            survived, outcome = False, f"{type(exc).__name__}: {exc}".splitlines()[0]
        cases.append({"name": name, "survived": bool(survived), "outcome": outcome,
                      "seconds": time.perf_counter() - t0})
    return cases


# ----------------------------------------------------------------------------- flood memory

_FLOOD_SERVER = r"""
import sys, time
from common.fitting import FitOptions
from server import cluster
def peak():
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM")) / 1024
if sys.argv[1] != "current":  # zmq takes the limit at bind
    cluster.MAX_CLIENT_MESSAGE_BYTES = int(sys.argv[1])
solver = cluster.ClusterSolver(FitOptions(), bind=cluster.LOCAL_BIND)
print(solver.endpoint, round(peak()), flush=True)
sys.stdin.readline()  # the flood was sent
deadline = time.monotonic() + 30
while time.monotonic() < deadline and not (solver.stats()["dropped"] or solver.stats()["disconnects"]):
    time.sleep(0.05)
print(round(peak()), solver.stats()["dropped"], solver.stats()["disconnects"], flush=True)
solver.close()
"""


def flood_peak_rss(max_frame: str = "current") -> dict:
    """Peak RSS (MB) of a server process before and after one message of FLOOD_PARTS frames of
    FLOOD_PART_BYTES; ``max_frame`` "current" or a per-frame limit in bytes to set instead."""
    server = subprocess.Popen([sys.executable, "-c", _FLOOD_SERVER, max_frame], cwd=REPO, env=_env(),
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        endpoint, before = server.stdout.readline().split()
        zctx = zmq.Context()
        try:
            s = zctx.socket(zmq.DEALER)
            s.linger = 0
            s.connect(endpoint)
            part = b"\0" * FLOOD_PART_BYTES  # one buffer sent FLOOD_PARTS times
            s.send_multipart([encode(Heartbeat())[0]] + [part] * FLOOD_PARTS)
            time.sleep(0.5)
            server.stdin.write("sent\n")
            server.stdin.flush()
            after = server.stdout.readline().split(maxsplit=1)
        finally:
            zctx.destroy(linger=0)
        server.wait(SUBPROCESS_TIMEOUT)
    finally:
        _stop([server])
    return {"max_frame": max_frame, "peak_rss_mb_before": int(before), "peak_rss_mb_after": int(after[0]),
            "outcome": after[1].strip()}


def main(argv=None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--measure-flood", action="store_true", help="also the flood's peak RSS, old and current limit")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="mocap-faults-") as tmp:
        cases = run_faults(Path(tmp))
    for c in cases:
        print(f"{'survived' if c['survived'] else 'FAILED  '} {c['seconds']:6.1f} s  {c['name']}: {c['outcome']}")
    if args.measure_flood:
        for limit in (str(OLD_MAX_FRAME_BYTES), "current"):
            print("flood", json.dumps(flood_peak_rss(limit)))
    return 0 if all(c["survived"] for c in cases) else 1


if __name__ == "__main__":
    sys.exit(main())
