"""Compare a cluster result folder with a single-process one of the same frames.

    python deploy/compare.py SINGLE CLUSTER [--frames N] [--tolerance 1e-9] [--expect-lost-client]

Prints the cluster run's summary (as ``mocap fit`` prints it), then single vs distributed side by
side: seconds per frame, evaluations, accuracy, each cluster process's compute / waiting /
transfer split, the reliability counters, and the largest pose parameter difference. Exits 1
when a frame is missing or written twice, the poses differ by more than the tolerance, or
(``--expect-lost-client``) the server never noticed a lost client.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from server.commands.fit import print_summary

TOLERANCE = 1e-9  # radians / metres: distributed and single-process runs share one algorithm


def read_poses(folder: Path) -> list[dict]:
    """Every line of poses.jsonl, in file order (a resumed run may repeat a torn last line)."""
    lines = (folder / "poses.jsonl").read_text().splitlines()
    return [json.loads(line) for line in lines if line.strip()]


def check(single: Path, cluster: Path, frames: int | None, tolerance: float) -> tuple[list[str], float]:
    """Problems found (empty: the runs agree) and the largest parameter difference."""
    problems = []
    ref = {r["frame"]: r["params"] for r in read_poses(single)}
    got = read_poses(cluster)
    seen: dict[int, list[float]] = {}
    for r in got:
        if r["frame"] in seen:
            problems.append(f"frame {r['frame']} written twice")
        seen[r["frame"]] = r["params"]
    if frames is not None and len(ref) != frames:
        problems.append(f"single-process run has {len(ref)} frames, expected {frames}")
    missing = sorted(set(ref) - set(seen))
    extra = sorted(set(seen) - set(ref))
    if missing:
        problems.append(f"cluster run lacks frames {missing}")
    if extra:
        problems.append(f"cluster run has frames the single run lacks: {extra}")
    worst = 0.0
    for f in sorted(set(ref) & set(seen)):
        a, b = ref[f], seen[f]
        if len(a) != len(b):
            problems.append(f"frame {f}: {len(b)} parameters, expected {len(a)}")
            continue
        worst = max(worst, max(abs(x - y) for x, y in zip(a, b)))
    if worst > tolerance:
        problems.append(f"poses differ by up to {worst:.3g} > {tolerance:g}")
    return problems, worst


def comparison_table(s: dict, c: dict, worst: float) -> str:
    def num(v, fmt):
        return "-" if v is None else format(v, fmt)

    rows = [("", "single", f"cluster ({c.get('clients', '?')} clients)"),
            ("frames", str(s["frames"]), str(c["frames"]))]
    for key, label, fmt in (("seconds_per_frame", "s/frame (median)", ".3f"),
                            ("mean_seconds_per_frame", "s/frame (mean)", ".3f"),
                            ("wall_seconds", "wall seconds", ".1f"),
                            ("evaluations_per_frame", "evaluations/frame", ".0f"),
                            ("mean_joint_error_mm", "mean joint error, mm", ".1f"),
                            ("max_joint_error_mm", "max joint error, mm", ".1f")):
        rows.append((label, num(s.get(key), fmt), num(c.get(key), fmt)))
    if s.get("seconds_per_frame") and c.get("seconds_per_frame"):
        rows.append(("speed-up (median s/frame)", "1.00", f"{s['seconds_per_frame'] / c['seconds_per_frame']:.2f}"))
    w0, w1 = max(len(r[0]) for r in rows), max(len(r[1]) for r in rows)
    lines = [f"  {a.ljust(w0)}  {b.rjust(w1)}  {d}" for a, b, d in rows]

    timing = c.get("timing", {})
    n = max(c.get("frames_fitted_this_run") or c["frames"], 1)
    procs = timing.get("processes", [])
    if procs:
        lines += ["", f"  {'cluster process':18} {'chains':>6} {'compute':>8} {'waiting':>8} {'transfer':>8}  s/frame"]
        for p in procs:
            lines.append(f"  {p['name'][:18]:18} {num(p.get('chains'), 'd'):>6} "
                         f"{p.get('compute_seconds', 0.0) / n:8.3f} {p.get('waiting_seconds', 0.0) / n:8.3f} "
                         f"{p.get('transfer_seconds', 0.0) / n:8.3f}")
    counters = {k: timing[k] for k in ("clients_seen", "lost_clients", "resent", "stalls", "local_chains",
                                       "disconnects", "dropped") if k in timing}
    if counters:
        lines += ["", "  cluster counters: " + ", ".join(f"{k} {v}" for k, v in counters.items())]
    lines += [f"  max |single - cluster| pose parameter difference: {worst:.3g}"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="deploy/compare.py", description=__doc__.splitlines()[0])
    ap.add_argument("single", type=Path, help="result folder of the single-process run")
    ap.add_argument("cluster", type=Path, help="result folder of the cluster run")
    ap.add_argument("--frames", type=int, default=None, help="frames both runs must have")
    ap.add_argument("--tolerance", type=float, default=TOLERANCE)
    ap.add_argument("--expect-lost-client", action="store_true",
                    help="a client was killed mid-run: the server must have counted it lost")
    ap.add_argument("--title", default="cluster run")
    args = ap.parse_args(argv)
    try:
        s = json.loads((args.single / "summary.json").read_text())
        c = json.loads((args.cluster / "summary.json").read_text())
        problems, worst = check(args.single, args.cluster, args.frames, args.tolerance)
    except (OSError, ValueError, KeyError) as exc:
        print(f"compare: error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.title}: {args.cluster}")
    print_summary(c, sys.stdout, args.cluster)
    print()
    print(f"single process ({args.single}) vs cluster:")
    print(comparison_table(s, c, worst))
    if args.expect_lost_client and not c.get("timing", {}).get("lost_clients"):
        problems.append("the server counted no lost client, so the kill did not happen mid-run")
    for p in problems:
        print(f"compare: FAIL: {p}", file=sys.stderr)
    if not problems:
        print(f"  every frame present once; poses equal to {args.tolerance:g}: OK")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
