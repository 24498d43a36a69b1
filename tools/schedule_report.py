"""Where a fit's evaluations go, stage by stage, and which proposer's start each schedule keeps.

    python tools/schedule_report.py SEQUENCE [mocap fit options] [--json FILE]

Runs ``mocap fit SEQUENCE --out <temporary folder> --quiet`` with the options given and
counts, for every stage of every schedule (``common.search``: TRACKING, LIMBS_LOST, REFINE,
SEARCH, ...), the starts fitted, their evaluations and the wall seconds of their fits (fits an
earlier schedule of the frame made, recalled from its memo, are not counted again), and
the evaluations and seconds the proposers spend themselves (limb re-detection's grids, an
arm's twists, a limb's other basins); and for every schedule run, the proposer whose start
ended lowest ("initial": the fit the schedule was given, such as a refinement's tracked fit;
"again" is a polish, so the start it polished came from an earlier stage). The poses are
the run's own: the counting only watches. Also prints the run's wall seconds and, with truth,
its joint error.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import common.search as search  # noqa: E402
import server.session as session  # noqa: E402  (calls run_schedule by the name it imported)

SPENDING_PROPOSERS = ("redetected", "twists", "basins")


def schedule_name(schedule) -> str:
    for name in ("TRACKING", "LIMBS_LOST", "SEARCH", "WIDE", "REFINE", "REFINE_SEARCH"):
        if schedule is getattr(search, name):
            return name
    for name in ("REFINE", "REFINE_SEARCH"):  # a frame with hops: AFTER_HOPS appended
        if schedule.stages[:-len(search.AFTER_HOPS.stages)] == getattr(search, name).stages:
            return name + "+AFTER_HOPS"
    return f"other ({len(schedule.stages)} stages)"


class Watcher:
    """Wraps common.search's fits and proposers (and server.session's name for run_schedule),
    counting what they spend and what wins; ``uninstall`` puts them back. Safe with a fit's
    threads: counts under a lock, each thread's schedule's starts apart."""

    def __init__(self):
        self.stages = defaultdict(lambda: {"starts": 0, "evaluations": 0, "seconds": 0.0})
        self.spent = defaultdict(lambda: {"evaluations": 0, "seconds": 0.0})
        self.winners = defaultdict(Counter)
        self._lock = threading.Lock()
        self._local = threading.local()  # origin: {start bytes: proposer} of this thread's schedule
        self._saved = None

    def install(self) -> None:
        fit_or_recall, run_schedule = search._fit_or_recall, search.run_schedule
        self._saved = (fit_or_recall, run_schedule, session.run_schedule, dict(search.PROPOSERS))
        watcher = self

        def counted_fits(ctx, jobs, keys, memo, drop=None, score=None):
            caller = sys._getframe(1).f_locals  # run_schedule's: the stage being run
            schedule, stage = caller["schedule"], caller["stage"]
            fresh = [k not in memo for k in keys]  # fits an earlier schedule made are recalled, not spent again
            t0 = time.perf_counter()
            fits = fit_or_recall(ctx, jobs, keys, memo, drop, score)
            key = (schedule_name(schedule), schedule.stages.index(stage),
                   "+".join(stage.proposers) + ":" + ",".join(stage.variants or ("as fitted",)))
            with watcher._lock:
                row = watcher.stages[key]
                row["starts"] += sum(fresh)
                row["evaluations"] += sum(f.evaluations for f, new in zip(fits, fresh) if new)
                row["seconds"] += time.perf_counter() - t0
            return fits

        def watched_schedule(ctx, schedule, initial=None, memo=None):
            outer = getattr(watcher._local, "origin", None)  # a schedule run inside another's proposer
            watcher._local.origin = origin = {}
            try:
                result = run_schedule(ctx, schedule, initial, memo)
            finally:
                watcher._local.origin = outer
            if initial is not None and np.array_equal(result.params, initial.params):
                won = "initial"
            elif result.start is None:
                won = "fitted by its proposer"
            else:
                won = origin.get(np.asarray(result.start, dtype=np.float64).tobytes(), "?")
            with watcher._lock:
                watcher.winners[schedule_name(schedule)][won] += 1
            return result

        def watched(name, proposer):
            def propose(ctx, source, spent, own):
                e0, t0 = spent.evaluations, time.perf_counter()
                starts = proposer(ctx, source, spent, own)
                if name in SPENDING_PROPOSERS:
                    with watcher._lock:
                        watcher.spent[name]["evaluations"] += spent.evaluations - e0
                        watcher.spent[name]["seconds"] += time.perf_counter() - t0
                origin = getattr(watcher._local, "origin", None)
                for start in starts:
                    if origin is not None and not isinstance(start, search.FrameResult):
                        origin.setdefault(np.asarray(start, dtype=np.float64).tobytes(), name)
                return starts
            return propose

        search._fit_or_recall = counted_fits
        search.run_schedule = session.run_schedule = watched_schedule
        for name, proposer in list(search.PROPOSERS.items()):
            search.PROPOSERS[name] = watched(name, proposer)

    def uninstall(self) -> None:
        if self._saved is not None:
            search._fit_or_recall, search.run_schedule, session.run_schedule, proposers = self._saved
            search.PROPOSERS.clear()
            search.PROPOSERS.update(proposers)
            self._saved = None

    def report(self) -> dict:
        return {"stages": [{"schedule": s, "stage": i, "proposers": p, **v} for (s, i, p), v in sorted(self.stages.items())],
                "proposers_spending": dict(self.spent),
                "winners": {s: dict(c.most_common()) for s, c in self.winners.items()}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python tools/schedule_report.py", description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", type=Path)
    p.add_argument("--json", type=Path, default=None, help="also write the counts there")
    args, fit_options = p.parse_known_args(argv)
    from server.cli import main as mocap

    watcher = Watcher()
    watcher.install()
    try:
        with tempfile.TemporaryDirectory(prefix="schedule-report-") as tmp:
            t0 = time.perf_counter()
            code = mocap(["fit", str(args.sequence), "--out", str(Path(tmp) / "fit"), "--quiet", *fit_options])
            wall = time.perf_counter() - t0
            if code:
                return code
            summary = json.loads((Path(tmp) / "fit" / "summary.json").read_text())
    finally:
        watcher.uninstall()
    report = watcher.report()
    report["fit"] = {"frames": summary["frames"], "wall_seconds": wall,
                     "mean_joint_error_mm": summary.get("mean_joint_error_mm"),
                     "max_joint_error_mm": summary.get("max_joint_error_mm")}
    fit = report["fit"]
    print(f"{fit['frames']} frames in {fit['wall_seconds']:.1f} s" + (
        f", joint error {fit['mean_joint_error_mm']:.2f} mm mean, {fit['max_joint_error_mm']:.2f} max"
        if fit["mean_joint_error_mm"] is not None else ""))
    total = sum(r["evaluations"] for r in report["stages"]) + sum(v["evaluations"] for v in report["proposers_spending"].values())
    print(f"{'schedule':26s} {'stage':>5s} {'proposers:variants':48s} {'starts':>7s} {'evaluations':>12s} {'share':>6s} {'s':>7s}")
    for r in report["stages"]:
        print(f"{r['schedule']:26s} {r['stage']:5d} {r['proposers']:48s} {r['starts']:7d} {r['evaluations']:12d} "
              f"{r['evaluations'] / max(total, 1):6.1%} {r['seconds']:7.1f}")
    for name, v in report["proposers_spending"].items():
        print(f"{'(proposer)':26s} {'':5s} {name:48s} {'':7s} {v['evaluations']:12d} "
              f"{v['evaluations'] / max(total, 1):6.1%} {v['seconds']:7.1f}")
    print("\nthe start each schedule kept, by proposer:")
    for schedule, won in report["winners"].items():
        print(f"  {schedule}: " + ", ".join(f"{k} {v}" for k, v in won.items()))
    if args.json:
        args.json.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
