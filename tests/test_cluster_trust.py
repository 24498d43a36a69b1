"""Hostile peers: no result is used unchecked, floods and stalling crowds cost little, a network
address needs CURVE, secret keys are private, and a client refused by CURVE says so. Each run
still ends with the single-process poses."""
import logging
import stat
import sys
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import zmq
import zmq.auth

from common.body import LIMB_CHAINS
from common.errors import UserError
from common.fitting import FitOptions
from common.protocol import (MAX_CLIENT_MESSAGE_BYTES, MAX_TEXT_CHARS, Error, Heartbeat, Register,
                             Result, Solve, encode)
from common.sequence import load_sequence
from server.cluster import DEADLINE_FACTOR, DEADLINE_FLOOR, LOCAL_BIND, ClusterSolver
from server.trust import check_bind, create_curve_keys, default_bind
from server.session import run_fit
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from reliability_faults import FakePeers  # noqa: E402  the fault suite's fake peers, in tests too
from test_cluster_support import (PY, ROOT, THREAD_HEARTBEAT, env, poses, records, reference_fit,
                                  thread_workers, wait_for)

TOLERANCE = 1e-9
OPTIONS = FitOptions(refine_passes=0)  # tracking: what reference_fit fits


@pytest.fixture(scope="module")
def seq_path(small_sequence):
    return small_sequence


@pytest.fixture(scope="module")
def reference(seq_path, tmp_path_factory):
    return reference_fit(seq_path, tmp_path_factory.mktemp("trust") / "single")


def random_result(rng):
    def answer(msg: Solve) -> Result:
        return Result(session=msg.session, frame=msg.frame, iteration=msg.iteration, request=msg.request,
                      chain=msg.chains[0], params=rng.uniform(-1.0, 1.0, 35).tolist(), energy=0.0,
                      energy_before=0.0, evaluations=1, iterations=1, cpu_seconds=0.0, wall_seconds=0.0)
    return answer


def fit(model, seq_path, out, solver, frames=None) -> dict:
    return run_fit(model, load_sequence(seq_path), out, OPTIONS, solver, max_frames=frames)


def check_complete(out, reference):
    assert [r["frame"] for r in records(out)] == list(range(len(reference)))
    assert np.abs(poses(out) - reference).max() <= TOLERANCE


@pytest.mark.timeout(120)
def test_poisoned_results_are_refused_and_the_sender_gets_no_more_work(model, seq_path, reference, tmp_path,
                                                                       caplog):
    caplog.set_level(logging.WARNING, logger="server.cluster")
    solver = ClusterSolver(OPTIONS, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    liar = None
    try:
        liar = FakePeers(solver.endpoint, 1, "liar", random_result(np.random.default_rng(0)))
        with thread_workers(model, solver.endpoint, 1):
            solver.wait_for_clients(2, timeout=10)
            summary = fit(model, seq_path, tmp_path, solver)
    finally:
        if liar:
            liar.close()
        solver.close(shutdown="done")
    check_complete(tmp_path, reference)
    timing = summary["timing"]
    # every answer it gave was refused; the ban came before the first round ended
    assert 1 <= timing["rejected"] <= len(liar.solves)
    assert {(m.frame, m.iteration) for m in liar.solves} == {(0, 0)}
    processes = {p["name"]: p for p in timing["processes"]}
    assert processes["liar-0"]["rejected"] == timing["rejected"] and processes["liar-0"]["accepted"] == 0
    assert processes["t1"]["rejected"] == 0 and processes["t1"]["accepted"] >= 1
    assert summary["clients"] == 1  # the liar did no work
    warnings = [r.getMessage() for r in caplog.records if "fails its check" in r.getMessage()]
    assert len(warnings) == 1 and "liar-0" in warnings[0], warnings


@pytest.mark.timeout(120)
def test_a_flood_of_frames_is_dropped_and_its_sender_forgotten(model, seq_path, reference, tmp_path):
    solver = ClusterSolver(OPTIONS, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    ctx = zmq.Context()
    try:
        with thread_workers(model, solver.endpoint, 1):
            solver.wait_for_clients(1, timeout=10)
            flood = ctx.socket(zmq.DEALER)
            flood.linger = 0
            flood.connect(solver.endpoint)
            flood.send_multipart(encode(Register(client_id="flood", cores=1, backends=("cpu",), version="0")))
            wait_for(lambda: solver.client_count() == 2, 10, "the flood peer to register")
            # every frame as large as the server takes, more frames than any message has
            part = b"\0" * MAX_CLIENT_MESSAGE_BYTES
            flood.send_multipart([encode(Heartbeat())[0]] + [part] * 20)
            wait_for(lambda: solver.stats()["dropped"].get("too_large"), 10, "the flood to be dropped")
            assert solver.client_count() == 1  # forgotten
            # one frame over the server's MAXMSGSIZE: zmq closes the connection before buffering it
            big = ctx.socket(zmq.DEALER)
            big.linger = 0
            big.connect(solver.endpoint)
            big.send_multipart([b"\0" * (MAX_CLIENT_MESSAGE_BYTES + 1)] * 3)
            wait_for(lambda: solver.stats()["disconnects"] >= 1, 10, "zmq to drop the oversized peer")
            summary = fit(model, seq_path, tmp_path, solver)
    finally:
        ctx.destroy(linger=0)
        solver.close(shutdown="done")
    check_complete(tmp_path, reference)
    assert summary["timing"]["dropped"] == {"too_large": 1}


def clean_seconds(model, seq_path, out) -> float:
    solver = ClusterSolver(OPTIONS, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    try:
        t0 = time.perf_counter()
        fit(model, seq_path, out, solver)
        return time.perf_counter() - t0
    finally:
        solver.close()


STALL_CLIENT_TIMEOUT = 2.0  # seconds: the deadline until a solve has been measured


@pytest.mark.timeout(180)
def test_twenty_peers_that_never_answer_cost_little(model, seq_path, reference, tmp_path):
    """Before: each round's chains went to fresh silent peers one timeout after another
    (4 chains, 20 peers: 5 timeouts in the first round), then the first round of each kind of
    job (whole fits, limb solves, limb searches) cost one ``client_timeout``. Now a chain that
    timed out goes to a client that delivered accepted work, or the server; the deadline follows
    the measured solves, and a kind nothing has measured the server measures itself (it solves
    one such job rather than wait): each round that finds fresh silent peers costs a few median
    solves."""
    clean = clean_seconds(model, seq_path, tmp_path / "clean")
    solver = ClusterSolver(OPTIONS, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT,
                           client_timeout=STALL_CLIENT_TIMEOUT)
    crowd = None
    try:
        crowd = FakePeers(solver.endpoint, 20, "silent")
        solver.wait_for_clients(20, timeout=10)
        t0 = time.perf_counter()
        summary = fit(model, seq_path, tmp_path / "out", solver)
        stalled = time.perf_counter() - t0
    finally:
        if crowd:
            crowd.close()
        solver.close()
    check_complete(tmp_path / "out", reference)
    timing = summary["timing"]
    kinds = len(solver.deadlines())
    assert 1 <= kinds <= 3 and timing["backup_chains"] <= kinds
    assert timing["stalls"] + timing["backup_chains"] == len(crowd.solves) == 20 and timing["lost_clients"] == 0
    assert summary["clients"] == 0  # registered, but none did any work
    # each round that finds fresh silent peers one measured deadline, no client_timeout
    rounds = -(-20 // len(LIMB_CHAINS))
    deadline = max([DEADLINE_FLOOR, *solver.deadlines()])
    assert deadline < STALL_CLIENT_TIMEOUT
    assert stalled < 2 * (clean + rounds * deadline), (stalled, clean, deadline)


def test_the_deadline_follows_the_measured_solves(model):
    solver = ClusterSolver(OPTIONS, bind=LOCAL_BIND, client_timeout=3.0)
    try:
        kind = ("limb", ())
        assert solver._deadline(kind) == 3.0  # nothing measured yet
        for seconds in (0.01, 0.02, 0.03):
            solver._measured(kind, seconds)
        assert solver._deadline(kind) == DEADLINE_FLOOR
        for seconds in (0.3, 0.3, 0.4, 0.5):
            solver._measured(kind, seconds)
        assert solver._deadline(kind) == pytest.approx(DEADLINE_FACTOR * 0.3)
        for seconds in (5.0,) * 10:
            solver._measured(kind, seconds)
        assert solver._deadline(kind) == 3.0  # never above --client-timeout
        assert solver._deadline(("hop", ())) == 3.0  # each kind of job on its own
    finally:
        solver.close()


def test_the_largest_client_message_fits_the_servers_frame_limit():
    text = "\U0001F600" * MAX_TEXT_CHARS  # 4 bytes each in UTF-8
    big = Error(code="x" * 128, text=text, session="s" * 128, frame=2**63 - 1, iteration=2**63 - 1,
                request=2**63 - 1)
    register = Register(client_id="\U0001F600" * 128, cores=4096, version="\U0001F600" * 128,
                        backends=tuple(f"{i:02d}" + "\U0001F600" * 126 for i in range(16)))
    for msg in (big, register):
        frames = encode(msg)
        assert len(frames) == 1 and len(frames[0]) * 3 < MAX_CLIENT_MESSAGE_BYTES


@pytest.mark.parametrize("bind", ["tcp://127.0.0.1:5555", "tcp://127.1.2.3:5555", "tcp://localhost:5555",
                                  "tcp://[::1]:5555", "ipc:///tmp/mocap.sock", "inproc://mocap"])
def test_loopback_and_ipc_need_no_keys(bind):
    assert check_bind(bind, None, insecure=False) is False


@pytest.mark.parametrize("bind", ["tcp://*:5555", "tcp://0.0.0.0:5555", "tcp://192.168.1.5:5555",
                                  "tcp://eth0:5555", "tcp://server.example:5555", "tcp://[::]:5555"])
def test_a_network_address_without_curve_is_refused_unless_insecure(bind, tmp_path):
    with pytest.raises(UserError, match="--curve-keys"):
        check_bind(bind, None, insecure=False)
    assert check_bind(bind, None, insecure=True) is True
    assert check_bind(bind, tmp_path, insecure=False) is False


def test_mocap_server_refuses_a_network_bind_without_keys(seq_path, tmp_path, capsys):
    from server.cli import main

    assert main(["server", str(seq_path), "--out", str(tmp_path / "out"), "--bind", "tcp://*:5555"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--curve-keys" in err and "--insecure" in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.timeout(60)
def test_mocap_server_without_bind_binds_where_it_may(seq_path, tmp_path, capsys):
    """No --bind: the loopback without keys (a default that always starts), every interface with
    them. The bind passes its check, so the first refusal is the earlier result's."""
    from server.cli import build_parser, main

    out = tmp_path / "out"
    out.mkdir()
    (out / "poses.jsonl").write_text("{}\n")
    assert main(["server", str(seq_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--overwrite" in err and "--bind" not in err, err
    keys = create_curve_keys(tmp_path / "keys")
    args = build_parser().parse_args(["server", str(seq_path), "--out", str(out)])
    assert args.bind is None  # resolved by mocap server from --curve-keys:
    assert default_bind(None) == "tcp://127.0.0.1:5555" and check_bind(default_bind(None), None, False) is False
    assert default_bind(keys) == "tcp://*:5555"


@pytest.mark.timeout(60)
@pytest.mark.parametrize("folder, said", [("missing", "no such folder; make the keys with: mocap keys {keys}"),
                                          ("empty", "{keys}/server.key_secret is missing; make the keys with: "
                                                    "mocap keys {keys}"),
                                          ("client", "a client's key folder"),
                                          # following "make the keys with" there would nest a second set
                                          ("allow-list", "holds client keys but no server.key_secret: the clients/ "
                                                         "allow-list? Give the folder mocap keys made ({made}, if so)"),
                                          ("file", "is a file")])
def test_mocap_server_says_a_key_folder_lacks_the_server_key(seq_path, tmp_path, capsys, folder, said):
    from server.cli import main

    keys = tmp_path / "keys"
    if folder == "empty":
        keys.mkdir()
    elif folder == "client":
        keys = create_curve_keys(tmp_path / "made") / "for-client"
    elif folder == "allow-list":
        keys = create_curve_keys(tmp_path / "made") / "clients"
    elif folder == "file":
        keys = create_curve_keys(tmp_path / "made") / "server.key"
    assert main(["server", str(seq_path), "--out", str(tmp_path / "out"), "--curve-keys", str(keys)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Invalid certificate" not in err, err
    assert err.startswith(f"mocap server: error: --curve-keys {keys}: ") and said.format(
        keys=keys, made=tmp_path / "made") in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.timeout(60)
def test_mocap_client_says_a_key_folder_lacks_its_key(tmp_path, capsys):
    from client.__main__ import main

    keys = create_curve_keys(tmp_path / "keys")
    assert main(["--connect", "tcp://127.0.0.1:1", "--curve-keys", str(keys / "clients")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Invalid certificate" not in err, err
    assert f"--curve-keys {keys / 'clients'}: no client.key_secret there" in err and "for-NAME" in err, err


def test_insecure_bind_is_logged_loudly(model, caplog, monkeypatch):
    import server.cluster as cluster

    # the check says a network address; the socket still binds the loopback (tests bind no other)
    monkeypatch.setattr(cluster, "check_bind", lambda bind, keys, insecure: True)
    caplog.set_level(logging.WARNING, logger="server.cluster")
    ClusterSolver(OPTIONS, bind=LOCAL_BIND, insecure=True).close()
    assert any("INSECURE" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("argv", [
    ["--min-clients", "-1"], ["--client-timeout", "0"], ["--client-timeout", "nan"], ["--heartbeat", "-1"],
    ["--heartbeat", "inf"],
])
def test_mocap_server_refuses_bad_numbers(seq_path, tmp_path, argv, capsys):
    from server.cli import main

    assert main(["server", str(seq_path), "--out", str(tmp_path / "out"), *argv]) == 2
    assert argv[0] in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["--reconnect-min", "-1"], ["--reconnect-max", "0"], ["--reconnect-min", "nan"],
    ["--reconnect-min", "5", "--reconnect-max", "1"], ["--test-stall", "-1"], ["--test-stall-requests", "0"],
])
def test_mocap_client_refuses_bad_numbers(argv, capsys):
    from client.__main__ import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--connect", "tcp://127.0.0.1:1", *argv])
    assert exit_info.value.code == 2
    assert argv[-2] in capsys.readouterr().err


def secret_modes(directory):
    return {str(p.relative_to(directory)): stat.S_IMODE(p.stat().st_mode) for p in directory.rglob("*.key_secret")}


def test_secret_key_files_are_private(tmp_path):
    keys = create_curve_keys(tmp_path / "keys", ("a", "b"))
    assert secret_modes(keys) == {"server.key_secret": 0o600, "client.key_secret": 0o600,
                                  "for-a/client.key_secret": 0o600, "for-b/client.key_secret": 0o600}
    assert sorted(p.name for p in (keys / "clients").iterdir()) == ["a.key", "b.key"]
    assert (keys / "server.key").exists() and [p.name for p in keys.iterdir() if p.name.startswith(".")] == []


def test_each_client_gets_a_folder_of_its_own_key(tmp_path):
    """``for-NAME/`` is what NAME's machine loads with --curve-keys: its own pair, whose public
    half is NAME's entry in the allow-list, and the server's public key (a copy of the whole
    folder would make every client the first one)."""
    from client.worker import CurveKeys

    keys = create_curve_keys(tmp_path / "keys", ("lab1", "lab2"))
    for name in ("lab1", "lab2"):
        loaded = CurveKeys.load(str(keys / f"for-{name}"))
        allowed, _ = zmq.auth.load_certificate(keys / "clients" / f"{name}.key")
        assert loaded.public == allowed
        assert loaded.server == zmq.auth.load_certificate(keys / "server.key")[0]
    assert CurveKeys.load(str(keys)).public == CurveKeys.load(str(keys / "for-lab1")).public


@pytest.mark.parametrize("names, said", [("a,a", "twice"), ("server", "server's own"), ("a,,b", "empty name"),
                                         ("../x", "letters, digits"), (",", "empty name")])
def test_mocap_keys_refuses_bad_client_names_before_making_anything(tmp_path, capsys, names, said):
    from server.cli import main

    assert main(["keys", str(tmp_path / "k"), "--clients", names]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--clients" in err and said in err and "Traceback" not in err
    assert not (tmp_path / "k").exists()


def test_mocap_keys_writes_private_secret_keys(tmp_path):
    from server.cli import main

    assert main(["keys", str(tmp_path / "k")]) == 0
    assert set(secret_modes(tmp_path / "k").values()) == {0o600}


@pytest.mark.parametrize("inside", ["", "clients", "for-client"])
def test_mocap_keys_refuses_a_folder_that_holds_keys(tmp_path, capsys, inside):
    from server.cli import main

    create_curve_keys(tmp_path / "k")
    folder = tmp_path / "k" / inside
    before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "k").rglob("*"))
    assert main(["keys", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already holds keys" in err, err
    assert sorted(p.relative_to(tmp_path) for p in (tmp_path / "k").rglob("*")) == before


@pytest.mark.parametrize("address, said", [("tcp://127.0.0.1:99999", "the port must be 1-65535"),
                                           ("127.0.0.1:5555", "expected tcp://HOST:PORT"),
                                           ("tcp://127.0.0.1", "expected tcp://HOST:PORT"),
                                           ("udp://127.0.0.1:5555", "expected tcp://HOST:PORT")])
def test_server_and_client_refuse_a_bad_address(seq_path, tmp_path, capsys, address, said):
    """ZeroMQ would bind port 99999 as 34463 and say only "Invalid argument" without the scheme."""
    from client.__main__ import main as client
    from server.cli import main

    assert main(["server", str(seq_path), "--out", str(tmp_path / "out"), "--bind", address]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--bind" in err and said in err, err
    with pytest.raises(SystemExit) as exit_info:
        client(["--connect", address])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--connect" in err and said in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.timeout(90)
def test_a_client_refused_by_curve_says_so_and_exits(model, tmp_path):
    keys = create_curve_keys(tmp_path / "keys")
    stranger = create_curve_keys(tmp_path / "stranger")  # a pair the server does not know
    (stranger / "server.key").write_bytes((keys / "server.key").read_bytes())
    solver = ClusterSolver(OPTIONS, bind=LOCAL_BIND, curve_keys=keys)
    try:
        proc = subprocess.run([PY, "-m", "client", "--connect", solver.endpoint, "--curve-keys", str(stranger),
                               "--reconnect-min", "0.2", "--quiet"],
                              cwd=ROOT, env=env(), capture_output=True, text=True, timeout=60)
        assert solver.client_count() == 0
    finally:
        solver.close()
    assert proc.returncode == 3, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "server refused the CURVE handshake" in last and "clients/ folder" in last, proc.stderr


@pytest.mark.timeout(60)
def test_mocap_server_refuses_an_earlier_result_before_sizing_the_actor(seq_path, tmp_path, capsys, monkeypatch):
    """A result in the way is refused at once, as mocap fit refuses it: not after the actor's size
    search, which may take minutes."""
    import server.commands.fit as fit
    from server.cli import main

    def no_search(*args, **kwargs):
        raise AssertionError("the size search ran before the folder was checked")

    monkeypatch.setattr(fit, "choose_actor_scale", no_search)
    out = tmp_path / "out"
    out.mkdir()
    (out / "poses.jsonl").write_text("{}\n")
    assert main(["server", str(seq_path), "--out", str(out), "--init", "auto", "--bind", "tcp://127.0.0.1:5555"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--overwrite" in err, err
    assert (out / "poses.jsonl").read_text() == "{}\n"


@pytest.mark.timeout(120)
def test_mocap_server_listens_while_it_sizes_the_actor(seq_path, tmp_path, monkeypatch):
    """The server binds before the actor's size search (which may take minutes on a real take),
    so clients and a container's health check find it meanwhile; the search runs on the
    server's --threads."""
    import socket

    import server.commands.fit as fit
    from server.cli import main
    from test_cluster_support import free_port

    port, seen = free_port(), []
    search = fit.choose_actor_scale

    def search_while_listening(*args, **kwargs):
        with socket.socket() as s:
            seen.append(s.connect_ex(("127.0.0.1", port)) == 0)
        threads.append(args[3])
        return search(*args, **kwargs)

    import server.commands.server as server_command

    class Recorded(server_command.ClusterSolver):
        def __init__(self, *args, **kwargs):
            threads.append(kwargs.get("threads"))
            super().__init__(*args, **kwargs)

    threads = []
    monkeypatch.setattr(fit, "choose_actor_scale", search_while_listening)
    monkeypatch.setattr(server_command, "ClusterSolver", Recorded)
    assert main(["server", str(seq_path), "--out", str(tmp_path / "out"), "--init", "auto", "--frames", "1",
                 "--refine-passes", "0", "--min-clients", "0", "--bind", f"tcp://127.0.0.1:{port}", "--quiet",
                 "--threads", "1"]) == 0
    assert seen == [True]
    assert threads == [1, 1]  # --threads: the server's own rounds', then the size search's
