"""Cluster timing: the same frames fitted single-process and by a server with N local clients,
beside the paper's Table 2 (Theobalt et al. 2003, sequence A).

    python -m server.bench_cluster SEQUENCE --frames 6 --json bench/cluster.json

Rows: single process without pre-rendering (the paper's XOR), single process (XORPR), server
+ N clients on this machine (distributed), and the critical-path speed-up a cluster of one
server and four client machines would get: the server's own work (torso, head, energy checks)
one after another, each round's jobs (limb solves, hops, whole fits of a round's starts) side by
side on the five machines (``critical_path``), against everything one after another, from the
single-process run's CPU seconds. Per-process compute / waiting / transfer seconds come from the
solvers; for the distributed run, the server's rounds (dispatched to all results checked) against
their jobs' CPU seconds, and its time alone between rounds, say where the wall time went.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from common.body import load_body_model
from common.fitting import FitOptions
from common.sequence import load_sequence
from common.argtypes import count
from server.local_cluster import LocalCluster
from server.results import load_records
from server.session import LocalSolver, run_fit
from server.threads import usable_cores

PAPER_TABLE2 = {  # seconds per frame, sequence A; 1.8 GHz Xeon + GeForce3 per machine
    "single_xor_seconds_per_frame": 7.98,
    "single_seconds_per_frame": 3.30,
    "distributed_seconds_per_frame": 1.16,  # server + 4 clients, 5 machines
}
DEFAULT_CLIENTS = 4
DEFAULT_REPEATS = 2  # alternating single / distributed runs; each frame's best time counts


class _PhaseClock:
    """Wraps a single-process solver and times, per dispatch round, the caller's thread: its own
    work before the round ("before": the torso, energy checks, proposals), its work while the
    round's jobs would run elsewhere ("during": the head), and each job's CPU seconds (limb
    solves, hops, whole fits: from their ChainResults)."""

    def __init__(self, inner):
        self.inner = inner
        self.mode, self.clients = inner.mode, inner.clients
        self.rounds: list[dict] = []  # {"frame", "before", "during", "jobs": [cpu seconds]}
        self._mark = time.thread_time()
        self._frame = None

    def begin_frame(self, frame, data, start, options):
        self._frame = int(frame)
        self.inner.begin_frame(frame, data, start, options)
        self._mark = time.thread_time()

    def solve(self, jobs, params, iteration, options=None):
        entry = {"frame": self._frame, "before": time.thread_time() - self._mark}
        self._mark = time.thread_time()
        collect = self.inner.solve(jobs, params, iteration, options)

        def timed_collect():
            entry["during"] = time.thread_time() - self._mark
            results = collect()
            entry["jobs"] = [r.cpu_seconds for r in results]
            self.rounds.append(entry)
            self._mark = time.thread_time()
            return results

        return timed_collect

    def workers(self):
        return self.inner.workers()

    def timing(self):
        return self.inner.timing()

    def close(self):
        self.inner.close()


CRITICAL_PATH_MACHINES = 5  # the paper's cluster: the server and four clients


def makespan(seconds: list[float], machines: int) -> float:
    """Seconds until ``machines`` finish jobs of these lengths, each taken by the first free
    machine, longest first (LPT scheduling)."""
    free = [0.0] * machines
    for t in sorted(seconds, reverse=True):
        k = int(np.argmin(free))
        free[k] += t
    return max(free) if seconds else 0.0


def shared_makespan(seconds: list[float], cores: int) -> float:
    """Seconds until jobs of these lengths finish when they all start at once and share
    ``cores`` cores equally (as an operating system runs more processes than cores): each runs
    at min(1, cores / jobs left) until the shortest left ends."""
    left, now = sorted(seconds), 0.0
    while left:
        rate = min(1.0, cores / len(left))
        now += left[0] / rate
        left = [t - left[0] for t in left[1:] if t - left[0] > 0.0]
    return now


def critical_path(rounds: list[dict], machines: int = CRITICAL_PATH_MACHINES, cores: int = 1) -> dict:
    """Per-frame serial and critical-path seconds from per-round CPU seconds: one process does
    everything one after another; ``machines`` do the server's own work in order and each
    round's jobs side by side (``makespan``). ``..._overlapped`` also runs the server's work
    during a round (the head) beside the jobs."""
    serial, critical, overlapped = {}, {}, {}
    shared = 0.0  # ``cores`` shared by each round's jobs, nothing lost to transfer
    for r in rounds:
        f, jobs = r["frame"], r["jobs"]
        spread = makespan(jobs, machines)
        serial[f] = serial.get(f, 0.0) + r["before"] + r["during"] + sum(jobs)
        critical[f] = critical.get(f, 0.0) + r["before"] + r["during"] + spread
        overlapped[f] = overlapped.get(f, 0.0) + r["before"] + max(r["during"], spread)
        shared += r["before"] + shared_makespan(jobs + [r["during"]], cores)
    frames = max(len(serial), 1)
    total_serial, total_critical = sum(serial.values()), sum(critical.values())
    return {
        "critical_path_machines": machines,
        "serial_seconds_per_frame": total_serial / frames,
        "critical_path_seconds_per_frame": total_critical / frames,
        "critical_path_speedup": total_serial / total_critical if total_critical else None,
        "critical_path_speedup_overlapped": (total_serial / sum(overlapped.values())
                                             if overlapped else None),
        "jobs_per_round": float(np.mean([len(r["jobs"]) for r in rounds])) if rounds else None,
        # what a cluster on one machine of ``cores`` cores would gain if nothing were lost to
        # transfer, checks and switching: each round's jobs (and the head beside them) sharing
        # the cores as the operating system shares them, the server's own work alone
        "shared_cores": cores,
        "shared_cores_speedup": total_serial / shared if shared else None,
    }


def _per_frame(processes: list[dict], frames: int) -> list[dict]:
    keys = ("compute_seconds", "waiting_seconds", "transfer_seconds", "cpu_seconds")
    return [{**{k: v for k, v in p.items() if k not in keys},
             **{k.replace("_seconds", "_seconds_per_frame"): p.get(k, 0.0) / max(frames, 1) for k in keys}}
            for p in processes]


def _params(out: Path) -> np.ndarray:
    return np.array([r["params"] for r in load_records(out)])


def _frame_seconds(out: Path) -> np.ndarray:
    return np.array([r["seconds"] for r in load_records(out)])


def _best_per_frame(runs: list[np.ndarray]) -> float:
    """Mean over frames of each frame's fastest time over the runs: other jobs on a shared
    machine only ever add time, so the minimum is the least disturbed measurement."""
    return float(np.min(np.stack(runs), axis=0).mean())


def bench_cluster(sequence, frames: int | None = None, clients: int = DEFAULT_CLIENTS,
                  options: FitOptions | None = None, xor: bool = True, repeats: int = DEFAULT_REPEATS,
                  out: Path | None = None) -> dict:
    """Fit the first ``frames`` frames of ``sequence`` single-process and with ``clients`` local
    clients, alternately ``repeats`` times (and once single-process without pre-rendering, if
    ``xor``); return the comparison."""
    model = load_body_model()
    seq = load_sequence(Path(sequence))
    options = options or FitOptions(refine_passes=0)  # the paper's Table 2 times tracking
    with tempfile.TemporaryDirectory(prefix="bench-cluster-") as tmp:
        root = Path(out) if out else Path(tmp)

        def single(opts: FitOptions, name: str):
            clock = _PhaseClock(LocalSolver(model, opts))
            cpu0 = time.process_time()
            summary = run_fit(model, seq, root / name, opts, clock, max_frames=frames)
            process = {"name": "server", "role": "server", "compute_seconds": summary["wall_seconds"],
                       "waiting_seconds": 0.0, "transfer_seconds": 0.0,
                       "cpu_seconds": time.process_time() - cpu0, "chains": None}
            return {"summary": summary, "clock": clock, "processes": [process],
                    "seconds": _frame_seconds(root / name)}

        def distributed(name: str):
            with LocalCluster(options, clients) as solver:
                summary = run_fit(model, seq, root / name, options, solver, max_frames=frames)
            return {"summary": summary, "processes": summary["timing"]["processes"],
                    "seconds": _frame_seconds(root / name)}

        singles, clusters = [], []
        for r in range(repeats):  # alternate, so both see the same background load
            singles.append(single(options, f"single-{r}"))
            clusters.append(distributed(f"distributed-{r}"))
        xor_run = single(replace(options, prerender=False), "single-xor") if xor else None
        difference = max(float(np.abs(_params(root / f"single-{r}") - _params(root / f"distributed-{r}")).max())
                         for r in range(repeats))

    n = len(singles[0]["seconds"])
    fastest_single = min(singles, key=lambda run: run["seconds"].sum())
    fastest_cluster = min(clusters, key=lambda run: run["seconds"].sum())
    result = {
        "sequence": str(sequence), "frames": n, "clients": clients, "repeats": repeats, "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()), "options": options.to_wire(),
        "single_seconds_per_frame": _best_per_frame([run["seconds"] for run in singles]),
        "single_xor_seconds_per_frame": float(xor_run["seconds"].mean()) if xor_run else None,
        "distributed_seconds_per_frame": _best_per_frame([run["seconds"] for run in clusters]),
        "runs_seconds_per_frame": {"single": [float(run["seconds"].mean()) for run in singles],
                                   "distributed": [float(run["seconds"].mean()) for run in clusters]},
        **critical_path(fastest_single["clock"].rounds, cores=usable_cores()),
        "processes": {"single": _per_frame(fastest_single["processes"], n),
                      "distributed": _per_frame(fastest_cluster["processes"], n)},
        "cluster_counters": {k: v for k, v in fastest_cluster["summary"]["timing"].items()
                             if k not in ("processes", "session", "endpoint")},
        "max_param_difference": difference,
        "paper_table2": dict(PAPER_TABLE2, speedup=PAPER_TABLE2["single_seconds_per_frame"]
                             / PAPER_TABLE2["distributed_seconds_per_frame"]),
    }
    result["speedup"] = result["single_seconds_per_frame"] / result["distributed_seconds_per_frame"]
    result["distributed_rounds"] = rounds_per_frame(fastest_cluster["processes"], n)
    return result


def rounds_per_frame(processes: list[dict], frames: int) -> dict:
    """Where a distributed run's wall time went, per frame, from its server's timing: rounds
    (dispatched to all results checked) against their jobs' CPU seconds, and the server alone
    between rounds (nothing out with the clients), and the rounds of short jobs it kept."""
    server = next(p for p in processes if p["role"] == "server")
    frames = max(frames, 1)
    return {"rounds_per_frame": server["rounds"] / frames, "jobs_per_frame": server["jobs"] / frames,
            "round_seconds_per_frame": server["round_seconds"] / frames,
            "round_job_cpu_seconds_per_frame": server["round_job_cpu_seconds"] / frames,
            "server_alone_seconds_per_frame": server["between_rounds_seconds"] / frames,
            "short_rounds_per_frame": server["short_rounds"] / frames,
            "short_jobs_per_frame": server["short_jobs"] / frames,
            "short_round_seconds_per_frame": server["short_round_seconds"] / frames}


DEFAULT_HOPS = 20


def bench_hops(sequence, frames: int | None = None, clients: int = DEFAULT_CLIENTS, hops: int = DEFAULT_HOPS,
               out: Path | None = None) -> list[dict]:
    """The refinement's hops (``--refine-hops``, one backward pass) over the first ``frames``
    frames of ``sequence``, single-process and with ``clients`` local clients running them side
    by side. One row per mode: {"mode", "clients", "frames", "refine_hops",
    "hop_seconds_per_frame" (in hop_fit alone), "hops_run_per_frame" (dropped hops too),
    "refine_seconds_per_frame" (the whole pass), "speedup" (single's hop seconds / this one's),
    "max_param_difference" (against single), "cpus"}."""
    model = load_body_model()
    seq = load_sequence(Path(sequence))
    options = FitOptions(refine_passes=1, refine_hops=hops)
    with tempfile.TemporaryDirectory(prefix="bench-hops-") as tmp:
        root = Path(out) if out else Path(tmp)
        single = run_fit(model, seq, root / "single", options, LocalSolver(model, options), max_frames=frames)
        with LocalCluster(options, clients) as solver:
            cluster = run_fit(model, seq, root / "distributed", options, solver, max_frames=frames)
        difference = float(np.abs(_params(root / "single") - _params(root / "distributed")).max())

    def hop_seconds(summary):
        return summary["refinement_passes"][0]["hop_seconds"] / summary["frames"]

    rows = []
    for mode, summary, n in (("single", single, 0), ("distributed", cluster, clients)):
        rows.append({"mode": mode, "clients": n, "frames": summary["frames"], "refine_hops": hops,
                     "hop_seconds_per_frame": hop_seconds(summary),
                     "hops_run_per_frame": summary["refinement_passes"][0]["hops_run"] / summary["frames"],
                     "refine_seconds_per_frame": summary["refine_seconds_per_frame"],
                     "speedup": hop_seconds(single) / hop_seconds(summary),
                     "max_param_difference": 0.0 if mode == "single" else difference,
                     "cpus": os.cpu_count()})
    return rows


def format_table(r: dict) -> str:
    paper = r["paper_table2"]

    def s(v):
        return "-" if v is None else f"{v:.3f}"

    rows = [
        ("", "paper, seq. A", "ours"),
        ("single process, XOR (s/frame)", s(paper["single_xor_seconds_per_frame"]),
         s(r["single_xor_seconds_per_frame"])),
        ("single process, XORPR (s/frame)", s(paper["single_seconds_per_frame"]), s(r["single_seconds_per_frame"])),
        ("distributed (s/frame)", f"{paper['distributed_seconds_per_frame']:.3f} (5 PCs)",
         f"{s(r['distributed_seconds_per_frame'])} (server + {r['clients']} clients, {r['cpus']} cores)"),
        ("speed-up, single / distributed", s(paper["speedup"]), s(r["speedup"])),
        ("critical-path speed-up, 5 machines", "-",
         f"{s(r['critical_path_speedup'])} (head overlapped: {s(r['critical_path_speedup_overlapped'])})"),
        (f"jobs sharing {r['shared_cores']} cores, nothing lost", "-", s(r.get("shared_cores_speedup"))),
    ]
    w0, w1 = max(len(a) for a, _, _ in rows), max(len(b) for _, b, _ in rows)
    lines = [f"{a.ljust(w0)}  {b.ljust(w1)}  {c}" for a, b, c in rows]
    lines += ["", f"serial {s(r['serial_seconds_per_frame'])} s/frame, critical path "
                  f"{s(r['critical_path_seconds_per_frame'])} on {r['critical_path_machines']} machines, "
                  f"{r['jobs_per_round']:.1f} jobs per round"]
    d = r["distributed_rounds"]
    lines += [f"distributed, per frame: {d['rounds_per_frame']:.1f} rounds of {d['jobs_per_frame']:.1f} jobs in all, "
              f"{d['round_seconds_per_frame']:.3f} s for {d['round_job_cpu_seconds_per_frame']:.3f} s of the jobs' CPU "
              f"({d['round_job_cpu_seconds_per_frame'] / r['shared_cores']:.3f} on {r['shared_cores']} cores); "
              f"the server alone between rounds {d['server_alone_seconds_per_frame']:.3f} s, "
              f"{d['short_rounds_per_frame']:.1f} rounds of {d['short_jobs_per_frame']:.1f} short jobs kept "
              f"({d['short_round_seconds_per_frame']:.3f} s)"]
    lines += ["", f"{'process'.ljust(16)} {'compute':>8} {'waiting':>8} {'transfer':>8}  s/frame"]
    for mode in ("single", "distributed"):
        for p in r["processes"][mode]:
            lines.append(f"{(mode[:4] + ' ' + p['name']).ljust(16)} {p['compute_seconds_per_frame']:8.3f} "
                         f"{p['waiting_seconds_per_frame']:8.3f} {p['transfer_seconds_per_frame']:8.3f}")
    runs = r["runs_seconds_per_frame"]
    lines += ["", f"max |single - distributed| parameter difference: {r['max_param_difference']:.3g}",
              f"{r['frames']} frames x {r['repeats']} alternating runs (each frame's best counts); "
              f"s/frame per run: single {', '.join(f'{v:.3f}' for v in runs['single'])}; "
              f"distributed {', '.join(f'{v:.3f}' for v in runs['distributed'])}",
              f"load average at the end {r['load_average'][0]:.2f}"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m server.bench_cluster", description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", type=Path)
    p.add_argument("--frames", type=count(1), default=None, help="first N frames (default all)")
    p.add_argument("--clients", type=count(1), default=DEFAULT_CLIENTS)
    p.add_argument("--iterations", type=count(1), default=FitOptions.max_iterations, help="rounds per frame")
    p.add_argument("--repeats", type=count(1), default=DEFAULT_REPEATS, help="alternating runs of each mode")
    p.add_argument("--no-xor", action="store_true", help="skip the single-process run without pre-rendering")
    p.add_argument("--json", type=Path, default=None, help="write the results here")
    args = p.parse_args(argv)
    result = bench_cluster(args.sequence, args.frames, args.clients,
                           FitOptions(max_iterations=args.iterations, refine_passes=0), xor=not args.no_xor,
                           repeats=args.repeats)
    print(format_table(result))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
