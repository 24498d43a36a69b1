"""Server + clients over real sockets on 127.0.0.1 give the single-process poses, and report timing."""
import json
import subprocess

import numpy as np
import pytest

from common.body import LIMB_CHAINS, load_body_model
from common.fitting import FitOptions
from common.sequence import load_sequence
from server.cluster import LOCAL_BIND, ClusterSolver
from server.session import run_fit
from test_cluster_support import (HEARTBEAT, PY, ROOT, THREAD_HEARTBEAT, TRACKING_ONLY, env, free_port, poses, records,
                                  reference_fit, start_client, start_server, stop, thread_workers)

TOLERANCE = 1e-9
EQUAL_FRAMES = 2  # of the small sequence's FRAMES: a second frame sends a second FRAME


@pytest.fixture(scope="module")
def seq_path(small_sequence):
    return small_sequence


@pytest.fixture(scope="module")
def reference(seq_path, tmp_path_factory):
    return reference_fit(seq_path, tmp_path_factory.mktemp("cluster") / "single")


@pytest.mark.timeout(60)
@pytest.mark.parametrize("n", [0, 1, 2, 4, 6])
def test_same_poses_as_single_process(n, model, seq_path, reference, tmp_path):
    """Tracking's jobs (the limbs of a round, the whole fits of its starts, the limbs'
    re-detection) handed to any number of clients, or none: the single-process poses."""
    options = FitOptions(refine_passes=0)
    solver = ClusterSolver(options, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    try:
        with thread_workers(model, solver.endpoint, n) as workers:
            solver.wait_for_clients(n, timeout=10)
            summary = run_fit(model, load_sequence(seq_path), tmp_path, options, solver, max_frames=EQUAL_FRAMES)
    finally:
        solver.close(shutdown="done")
    got = poses(tmp_path)
    assert got.shape == (EQUAL_FRAMES, 35)
    assert np.abs(got - reference[:EQUAL_FRAMES]).max() <= TOLERANCE
    assert [r["frame"] for r in records(tmp_path)] == list(range(EQUAL_FRAMES))
    timing = summary["timing"]
    assert summary["mode"] == "cluster" and summary["clients"] == n
    clients = [p for p in timing["processes"] if p["role"] == "client"]
    assert len(clients) == n
    limb_solves = sum(s["chain"] in LIMB_CHAINS for r in records(tmp_path) for s in r["solves"])
    whole_fits = sum(r["whole_fits"] for r in records(tmp_path))
    assert limb_solves >= len(LIMB_CHAINS) and whole_fits >= 3 * EQUAL_FRAMES  # the start and its two turns
    # every job was done by a client or by the server, most by clients where there are some; the
    # server may also solve one job of a kind nothing has measured, which a client took a while
    # over, and keeps the rounds of jobs shorter than a hand-over (short_jobs)
    server = next(p for p in timing["processes"] if p["role"] == "server")
    done = sum(p["chains"] for p in clients) + timing["local_chains"] + server["short_jobs"]
    assert limb_solves + whole_fits <= done <= limb_solves + whole_fits + timing["backup_chains"]
    if n >= len(LIMB_CHAINS):
        assert timing["local_chains"] <= whole_fits + timing["backup_chains"]
    assert timing["dropped"] == {} and timing["resent"] == 0
    assert timing["rejected"] == 0 and all(p["rejected"] == 0 for p in clients)  # honest results check
    for p in timing["processes"]:
        for k in ("compute_seconds", "waiting_seconds", "transfer_seconds"):
            assert p[k] >= 0.0
    # its rounds, sent or kept: every job was in one, and each took time and CPU
    assert server["rounds"] + server["short_rounds"] >= 2 * EQUAL_FRAMES
    assert server["jobs"] + server["short_jobs"] >= limb_solves + whole_fits
    assert server["round_seconds"] > 0.0 and server["round_job_cpu_seconds"] > 0.0
    assert server["between_rounds_seconds"] > 0.0  # torso and head, and each new frame
    assert all(w.dropped == {} for w in workers)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("factor", [0.0, 1e9])
def test_short_rounds_stay_on_the_server(monkeypatch, model, seq_path, reference, tmp_path, factor):
    """Rounds the server's own threads solve sooner than the clients stay on the server, with
    the same poses: none where a hand-over counts for nothing, every round of a kind once
    measured where it counts for everything (the clients then solve only the first jobs of
    each kind)."""
    from server import cluster

    monkeypatch.setattr(cluster, "SHORT_JOB_FACTOR", factor)
    options = FitOptions(refine_passes=0)
    solver = ClusterSolver(options, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT, threads=2)
    try:
        with thread_workers(model, solver.endpoint, 2):
            solver.wait_for_clients(2, timeout=10)
            summary = run_fit(model, load_sequence(seq_path), tmp_path, options, solver, max_frames=EQUAL_FRAMES)
    finally:
        solver.close(shutdown="done")
    assert np.abs(poses(tmp_path) - reference[:EQUAL_FRAMES]).max() <= TOLERANCE
    server = next(p for p in summary["timing"]["processes"] if p["role"] == "server")
    sent = sum(p["chains"] for p in summary["timing"]["processes"] if p["role"] == "client")
    if factor == 0.0:
        assert server["short_rounds"] == server["short_jobs"] == 0 and server["rounds"] > 0
    else:
        assert server["short_rounds"] > server["rounds"] and server["short_jobs"] > sent
        assert server["short_round_seconds"] > 0.0


@pytest.mark.timeout(30)
def test_a_round_stays_where_it_is_solved_sooner():
    """The rule, from measured seconds: a round stays where its jobs over the server's threads
    take less than one job and a hand-over; nothing stays before both are measured, with one
    thread, or where a round mixes in a kind nothing has measured."""
    from collections import deque

    limb, fit, new = ("limb", ()), ("fit", ()), ("search", ())
    for threads, kinds, expected in [
        (2, [limb] * 4, True),        # 2 x 3 ms against 3 + 5 ms
        (2, [fit] * 5, False),        # 3 x 30 ms against 30 + 5 ms
        (2, [limb] * 8, False),       # 4 x 3 ms against 3 + 5 ms
        (4, [limb] * 8, True),        # 2 x 3 ms against 3 + 5 ms
        (2, [limb, limb, fit], False),  # the longest kind counts: 2 x 30 against 30 + 5
        (2, [limb, new], False),      # a kind not yet measured goes out
        (1, [limb] * 4, False),       # one thread keeps nothing
    ]:
        solver = ClusterSolver(FitOptions(), bind=LOCAL_BIND, threads=threads)
        try:
            with solver._lock:
                solver._job_cpu[limb].extend([0.002, 0.003, 0.004])
                solver._job_cpu[fit].extend([0.030])
                assert not solver._short([limb] * 4)  # no hand-over measured yet
                solver._handovers.extend([0.004, 0.005, 0.009])
                assert solver._short(kinds) == expected, (threads, kinds)
        finally:
            solver.close()


def fit_on_two_clients(model, seq, out, options) -> dict:
    """``run_fit`` of ``seq`` into ``out`` by a server and two clients on threads; its summary."""
    solver = ClusterSolver(options, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    try:
        with thread_workers(model, solver.endpoint, 2):
            solver.wait_for_clients(2, timeout=10)
            return run_fit(model, seq, out, options, solver)
    finally:
        solver.close(shutdown="done")


@pytest.mark.timeout(300)
@pytest.mark.parametrize("search, hops", [(False, 0), (True, 0), (False, 10)])
def test_refinement_passes_same_poses_as_single_process(model, seq_path, tmp_path, search, hops):
    """Tracking, then a backward and a forward pass (the first plain, searching limbs' other
    basins, or hopping, the clients running hops side by side), with two clients: each frame's poses and which frames
    the passes replaced are the single process's. Three frames, so that going backwards a
    client is sent a frame older than the two it holds."""
    from common.search import PASS_START_HOPS
    from server.session import LocalSolver

    options = FitOptions(refine_passes=2, refine_search=search, refine_hops=hops)
    seq = load_sequence(seq_path)
    single = run_fit(model, seq, tmp_path / "single", options, LocalSolver(model, options))
    cluster = fit_on_two_clients(model, seq, tmp_path / "cluster", options)
    assert cluster["frames"] == len(seq.frames) == 3
    np.testing.assert_array_equal(poses(tmp_path / "cluster"), poses(tmp_path / "single"))
    assert cluster["timing"]["rejected"] == 0  # limb solves, searches and hops: honest results check
    assert [p["frames_replaced"] for p in cluster["refinement_passes"]] == \
        [p["frames_replaced"] for p in single["refinement_passes"]]
    assert [p["direction"] for p in cluster["refinement_passes"]] == ["backward", "forward"]
    # the finish's evolutions went to the clients too, and lowered the same frames
    assert cluster["frames_finished"] == single["frames_finished"]
    # the plain forward pass starts with PASS_START_HOPS hops, side by side on the cluster too
    assert single["refinement_passes"][1]["hops_run"] == PASS_START_HOPS
    assert cluster["refinement_passes"][1]["hops_run"] >= PASS_START_HOPS
    if hops:  # every frame's hops: one after another in one process; three at a time (two
        # clients and the server), some dropped
        assert single["refinement_passes"][0]["hops_run"] == hops * 3
        assert cluster["refinement_passes"][0]["hops_run"] > hops * 3
        assert cluster["refinement_passes"][0]["hop_seconds"] > 0
        # the hops are not chains: the per-chain figures are tracking's and the refits'
        assert set(cluster["chain_cpu_seconds_per_frame"]) == set(single["chain_cpu_seconds_per_frame"]) == \
            {"torso", "head", *LIMB_CHAINS}


@pytest.mark.slow  # whole first-frame searches: make test-slow
@pytest.mark.timeout(240)
def test_automatic_start_same_poses_as_single_process(model, seq_path, tmp_path, monkeypatch):
    """The first frame's search fits several starts with wide options, then refines with the
    tracking options: clients must be told each switch (a FRAME per switch). Three of the
    voxel starts are enough for that (the search's later steps all run)."""
    from server import session
    from server.session import LocalSolver

    all_starts = session.voxel_starts
    monkeypatch.setattr(session, "voxel_starts", lambda model, data: all_starts(model, data)[:3])
    options = FitOptions()
    seq = load_sequence(seq_path)
    run_fit(model, seq, tmp_path / "single", options, LocalSolver(model, options), init="auto", max_frames=1)
    solver = ClusterSolver(options, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    try:
        with thread_workers(model, solver.endpoint, 2):
            solver.wait_for_clients(2, timeout=10)
            run_fit(model, seq, tmp_path / "cluster", options, solver, init="auto", max_frames=1)
    finally:
        solver.close(shutdown="done")
    np.testing.assert_array_equal(poses(tmp_path / "cluster"), poses(tmp_path / "single"))


@pytest.mark.timeout(60)
def test_with_no_clients_the_server_solves_everything(model, seq_path, reference, tmp_path):
    options = FitOptions()
    solver = ClusterSolver(options, bind=LOCAL_BIND, heartbeat_interval=HEARTBEAT)
    try:
        summary = run_fit(model, load_sequence(seq_path), tmp_path, options, solver, max_frames=1)
    finally:
        solver.close()
    assert np.abs(poses(tmp_path) - reference[:1]).max() <= TOLERANCE
    record = records(tmp_path)[0]
    limb_solves = sum(s["chain"] in LIMB_CHAINS for s in record["solves"])
    assert limb_solves > 0 and summary["timing"]["local_chains"] == limb_solves + record["whole_fits"]


@pytest.mark.timeout(60)
def test_mocap_fit_with_local_clients(seq_path, reference, tmp_path):
    out = tmp_path / "fit"
    proc = subprocess.run([PY, "-m", "server.cli", "fit", str(seq_path), "--out", str(out), "--clients", "2",
                           "--heartbeat", str(HEARTBEAT), "--quiet", *TRACKING_ONLY],
                          cwd=ROOT, env=env(), capture_output=True, text=True, timeout=50)
    assert proc.returncode == 0, proc.stderr
    assert np.abs(poses(out) - reference).max() <= TOLERANCE
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "cluster" and summary["clients"] == 2
    assert {p["name"] for p in summary["timing"]["processes"]} == {"server", "local-1", "local-2"}
    assert (out / "motion.bvh").exists()


@pytest.mark.timeout(120)
def test_an_actor_of_another_size_fitted_by_clients(seq_path, tmp_path):
    """An actor whose size is not the body model's (here given, --actor-height; chosen by the
    first frame where none is): `mocap fit --clients 2` and `mocap server` with a client started
    on its own, both with the body model at its own size, give the single process's poses, and
    the clients do the work (none of their results refused)."""
    sized = ("--actor-height", "1.9", "--frames", "2", "--heartbeat", str(HEARTBEAT), "--quiet", *TRACKING_ONLY)

    def fit(out, *extra):
        proc = subprocess.run([PY, "-m", "server.cli", "fit", str(seq_path), "--out", str(out), *sized, *extra],
                              cwd=ROOT, env=env(), capture_output=True, text=True, timeout=100)
        assert proc.returncode == 0, proc.stderr
        return json.loads((out / "summary.json").read_text())

    single = fit(tmp_path / "single")
    assert abs(single["actor_scale"] - 1.9 / load_body_model().height) < 1e-6
    clients = fit(tmp_path / "clients", "--clients", "2")
    port = free_port()
    server = start_server(seq_path, tmp_path / "server", port, tmp_path / "server.log", "--min-clients", "1",
                          "--actor-height", "1.9", "--frames", "2")
    client = start_client(f"tcp://127.0.0.1:{port}", "own", tmp_path / "client.log")
    try:
        assert server.wait(90) == 0, (tmp_path / "server.log").read_text()
    finally:
        stop([server, client])
    served = json.loads((tmp_path / "server" / "summary.json").read_text())
    for out, summary in ((tmp_path / "clients", clients), (tmp_path / "server", served)):
        assert np.abs(poses(out) - poses(tmp_path / "single")).max() <= TOLERANCE
        assert summary["actor_scale"] == single["actor_scale"]
        workers = [p for p in summary["timing"]["processes"] if p["role"] == "client"]
        assert workers and sum(p["chains"] for p in workers) > 0
        assert summary["timing"]["rejected"] == 0 and all(p["rejected"] == 0 for p in workers)


def test_mocap_fit_refuses_negative_clients(seq_path, tmp_path):
    proc = subprocess.run([PY, "-m", "server.cli", "fit", str(seq_path), "--out", str(tmp_path), "--clients", "-1"],
                          cwd=ROOT, env=env(), capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2 and "--clients" in proc.stderr


@pytest.mark.timeout(180)
def test_threads_give_the_single_threads_poses(model, seq_path, tmp_path):
    """One process fitting starts, limbs and hops three at a time: tracking and a refinement
    pass with hops give the one thread's poses, and the same frames replaced."""
    from server.session import LocalSolver

    options = FitOptions(refine_passes=1, refine_hops=4)
    seq = load_sequence(seq_path)
    one = run_fit(model, seq, tmp_path / "one", options, LocalSolver(model, options, threads=1))
    solver = LocalSolver(model, options, threads=3)
    try:
        three = run_fit(model, seq, tmp_path / "three", options, solver)
    finally:
        solver.close()
    np.testing.assert_array_equal(poses(tmp_path / "three"), poses(tmp_path / "one"))
    assert (one["threads"], three["threads"]) == (1, 3) and three["mode"] == "single"
    assert [p["frames_replaced"] for p in three["refinement_passes"]] == \
        [p["frames_replaced"] for p in one["refinement_passes"]]
    assert three["refinement_passes"][0]["hops_run"] >= one["refinement_passes"][0]["hops_run"]


@pytest.mark.timeout(300)
def test_chunked_refinement_same_poses_for_threads_and_clients(model, seq_path, tmp_path):
    """A refinement in chunks of one frame: side by side on three threads, one after another on
    one thread, and with two clients taking each frame's jobs: the same poses."""
    from server.session import LocalSolver

    options = FitOptions(refine_passes=2, refine_chunk_frames=1)
    seq = load_sequence(seq_path)
    runs = {}
    for threads in (1, 3):
        solver = LocalSolver(model, options, threads=threads)
        try:
            runs[threads] = run_fit(model, seq, tmp_path / f"threads-{threads}", options, solver)
        finally:
            solver.close()
    solver = ClusterSolver(options, bind=LOCAL_BIND, heartbeat_interval=THREAD_HEARTBEAT)
    try:
        with thread_workers(model, solver.endpoint, 2):
            solver.wait_for_clients(2, timeout=10)
            runs["cluster"] = run_fit(model, seq, tmp_path / "cluster", options, solver)
    finally:
        solver.close(shutdown="done")
    np.testing.assert_array_equal(poses(tmp_path / "threads-3"), poses(tmp_path / "threads-1"))
    np.testing.assert_array_equal(poses(tmp_path / "cluster"), poses(tmp_path / "threads-1"))
    assert len({tuple(p["frames_replaced"] for p in r["refinement_passes"]) for r in runs.values()}) == 1


def test_thread_count_from_the_environment(monkeypatch):
    from common.errors import UserError
    from server.threads import THREADS_ENV, resolve_threads, usable_cores

    monkeypatch.delenv(THREADS_ENV, raising=False)
    assert resolve_threads(0, FitOptions()) == usable_cores()
    assert resolve_threads(3, FitOptions()) == 3
    assert resolve_threads(3, FitOptions(energy="gl")) == 1  # one GL context, one thread
    monkeypatch.setenv(THREADS_ENV, "1")
    assert resolve_threads(0, FitOptions()) == 1 and resolve_threads(2, FitOptions()) == 2
    monkeypatch.setenv(THREADS_ENV, "many")
    with pytest.raises(UserError, match=THREADS_ENV):
        resolve_threads(0, FitOptions())


def test_mocap_fit_refuses_negative_threads(seq_path, tmp_path):
    proc = subprocess.run([PY, "-m", "server.cli", "fit", str(seq_path), "--out", str(tmp_path), "--threads", "-1"],
                          cwd=ROOT, env=env(), capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2 and "--threads" in proc.stderr and "Traceback" not in proc.stderr


def test_server_refuses_a_busy_address(model):
    from common.errors import UserError

    first = ClusterSolver(FitOptions(), bind=LOCAL_BIND)
    try:
        with pytest.raises(UserError, match="--bind"):
            ClusterSolver(FitOptions(), bind=first.endpoint).close()
    finally:
        first.close()


@pytest.mark.timeout(120)
def test_bench_cluster_reports_the_comparison(seq_path):
    from server.bench_cluster import bench_cluster, format_table

    r = bench_cluster(seq_path, frames=1, clients=2, options=FitOptions(max_iterations=1), xor=False)
    for key in ("single_seconds_per_frame", "distributed_seconds_per_frame", "clients", "critical_path_speedup"):
        assert r[key] is not None
    assert r["clients"] == 2 and r["max_param_difference"] <= TOLERANCE
    assert r["critical_path_speedup"] > 1.0
    names = [p["name"] for p in r["processes"]["distributed"]]
    assert names == ["server", "local-1", "local-2"]
    assert r["jobs_per_round"] >= 3  # the whole fits of a frame's starts, the four limbs of a round
    assert r["serial_seconds_per_frame"] > r["critical_path_seconds_per_frame"] > 0
    assert 1.0 <= r["shared_cores_speedup"] <= r["shared_cores"] + 1e-9
    rounds = r["distributed_rounds"]
    assert rounds["rounds_per_frame"] >= 2 and rounds["jobs_per_frame"] >= 3 * rounds["rounds_per_frame"] - 1e-9
    assert rounds["round_seconds_per_frame"] > 0 and rounds["round_job_cpu_seconds_per_frame"] > 0
    assert rounds["server_alone_seconds_per_frame"] > 0
    table = format_table(r)
    assert "3.300" in table and "1.160" in table and "nothing lost" in table
    assert "the server alone between rounds" in table


def test_jobs_sharing_cores_end_when_the_cores_have_done_their_work():
    from server.bench_cluster import shared_makespan

    assert shared_makespan([1.0, 1.0], 2) == pytest.approx(1.0)
    assert shared_makespan([1.0, 1.0, 1.0, 1.0], 2) == pytest.approx(2.0)
    assert shared_makespan([1.0, 1.0, 1.0], 2) == pytest.approx(1.5)  # each at two thirds
    assert shared_makespan([3.0, 1.0], 2) == pytest.approx(3.0)  # the long job alone at the end
    assert shared_makespan([2.0, 1.0, 1.0], 2) == pytest.approx(2.5)  # 1.5 shared, then 1 alone
    assert shared_makespan([], 2) == 0.0 and shared_makespan([2.0], 1) == pytest.approx(2.0)


@pytest.mark.timeout(240)
def test_bench_hops_runs_them_side_by_side_with_the_same_poses(seq_path, tmp_path, capsys):
    """``mocap bench hops``: local clients (real processes) run the hops side by side, with the
    single process's poses; dropped hops show as more hops run per frame."""
    from server.cli import main

    out = tmp_path / "hops.json"
    assert main(["bench", "hops", str(seq_path), "--frames", "2", "--clients", "2", "--hops", "4",
                 "--json", str(out)]) == 0
    single, distributed = json.loads(out.read_text())
    assert (single["mode"], single["clients"], distributed["mode"], distributed["clients"]) == \
        ("single", 0, "distributed", 2)
    assert distributed["max_param_difference"] == 0.0 and single["hops_run_per_frame"] == 4
    assert single["speedup"] == 1.0 and distributed["speedup"] > 0
    assert main(["bench", "hops", str(seq_path), "--hops", "0"]) == 2
    assert "--hops >= 1" in capsys.readouterr().err


def test_fit_table_shows_the_servers_rounds_per_frame():
    from server.commands.fit import _cluster_rows

    server = {"name": "server", "compute_seconds": 2.0, "waiting_seconds": 1.0, "transfer_seconds": 0.1, "chains": 3,
              "rounds": 40, "jobs": 170, "round_seconds": 2.4, "round_job_cpu_seconds": 4.0,
              "between_rounds_seconds": 0.2, "short_rounds": 18}
    client = {"name": "local-1", "compute_seconds": 1.0, "waiting_seconds": 0.5, "transfer_seconds": 0.2, "chains": 9}
    rows = dict(_cluster_rows({"frames_fitted_this_run": 10, "timing": {"processes": [server, client]}}))
    assert rows["rounds"] == ("4.0 a frame, 0.240 s for 0.400 s of their jobs' CPU; the server alone between "
                              "them 0.020 s/frame, 1.8 rounds of short jobs kept")
    assert rows["local-1 compute/wait/transfer"] == "0.100 / 0.050 / 0.020 s/frame, 9 chains"


@pytest.mark.timeout(300)
def test_masks_cleared_after_the_passes_give_the_same_poses_on_a_cluster(model, seq_path, tmp_path, monkeypatch):
    """Foreground no fitted pose explains is cleared once the take is fitted and the take refined
    again against the cleared masks (``leave_out_unexplained``): a frame's masks change under
    the same frame number, and the clients must be sent them again and use them (a client held
    a frame's masks by its number, and refined the next round's first frame against the old)."""
    import common.consistency as consistency
    from server.session import LocalSolver

    # the small take's body model misses the skinned actor's edges in every frame: cleared here
    monkeypatch.setattr(consistency, "UNEXPLAINED_MIN_FRAMES", 3)
    monkeypatch.setattr(consistency, "UNEXPLAINED_MIN_AREA", 0.0)
    options = FitOptions(refine_passes=1)
    seq = load_sequence(seq_path)
    single = run_fit(model, seq, tmp_path / "single", options, LocalSolver(model, options))
    assert single["foreground_left_out"]["share"] > 0 and (tmp_path / "single" / "foreground_left_out.npz").is_file()
    left_out = single["foreground_left_out"]  # what each round added, adding up to what was cleared
    assert sum(left_out["round_shares"]) == pytest.approx(left_out["share"], abs=1e-3)
    # the fit against the masks before the clearing too: the cleared pixels count there
    segmented = left_out["fit_quality_before_clearing"]
    assert segmented["mean_xor_share"] > single["fit_quality"]["mean_xor_share"]
    assert set(segmented["per_camera_mean_xor_share"]) == set(seq.studio.names)
    # the pictures draw the masks the fit had: the same pixels cleared
    from common.errors import InputFileError
    from server.pictures import load_result
    from server.results import read_foreground_left_out, write_foreground_left_out

    shown = load_result(tmp_path / "single").sequence
    cleared = read_foreground_left_out(tmp_path / "single")
    assert cleared.any() and not (shown.silhouettes(seq.frames[0]) & cleared).any()
    write_foreground_left_out(tmp_path / "other", cleared[:2])  # another take's
    (tmp_path / "other" / "poses.jsonl").write_text((tmp_path / "single" / "poses.jsonl").read_text())
    (tmp_path / "other" / "run.json").write_text((tmp_path / "single" / "run.json").read_text())
    with pytest.raises(InputFileError, match="not the sequence this result was fitted to"):
        load_result(tmp_path / "other")
    cluster = fit_on_two_clients(model, seq, tmp_path / "cluster", options)
    np.testing.assert_array_equal(poses(tmp_path / "cluster"), poses(tmp_path / "single"))
    assert cluster["foreground_left_out"] == single["foreground_left_out"]
    assert cluster["timing"]["rejected"] == 0
