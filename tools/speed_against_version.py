"""This version's speed against an earlier one's, on this machine, in the same hour.

    python tools/speed_against_version.py REV [--frames 100] [--repeats 2] [--fit-args "--preset fast"]
                                               [--sequence SEQ] [--json FILE]

This machine's speed changes by a third from hour to hour and from one machine to the next, so
a target in seconds (the default preset's 0.8 s per frame) is only comparable as a ratio
against a version measured beside it. REV (a commit, e.g. the one an issue was filed against)
is checked out into a temporary git worktree; both versions then fit the same sequence (default:
100 walk frames, `mocap synth --frames 100 --step 4 --noise cheung`) with `mocap fit SEQ --out R
--init auto` and their own default settings (plus ``--fit-args`` for this version), alternately
``--repeats`` times after a short run of each that compiles their kernels. Wall seconds are the
whole command's (actor size, first-frame search, tracking, refinement, start-up). Prints one
JSON object: per version the runs' seconds per frame, the best, the mean / max joint error;
and the speed-up, earlier best over this version's best.
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WARM_UP_FRAMES = 2  # a run this short compiles (and caches) a version's numba kernels


def mocap(cwd: Path, *args: str) -> None:
    """``python -m server.cli ARGS`` with ``cwd``'s packages (they come first on sys.path)."""
    out = subprocess.run([sys.executable, "-m", "server.cli", *args], cwd=cwd, capture_output=True, text=True)
    if out.returncode:
        raise SystemExit(f"mocap {' '.join(args)} in {cwd} failed ({out.returncode}): {out.stderr.strip()[-500:]}")


def timed_fit(cwd: Path, seq: Path, out: Path, frames: int, extra: list[str]) -> dict:
    t0 = time.perf_counter()
    mocap(cwd, "fit", str(seq), "--out", str(out), "--init", "auto", "--frames", str(frames), "--quiet", *extra)
    wall = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text())
    return {"seconds_per_frame": wall / summary["frames"], "mean_joint_error_mm": summary.get("mean_joint_error_mm"),
            "max_joint_error_mm": summary.get("max_joint_error_mm")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rev", help="the earlier version: a commit or tag")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=2, help="alternating runs of each version")
    ap.add_argument("--sequence", type=Path, default=None, help="default: 100 synthesised walk frames")
    ap.add_argument("--fit-args", default="", help="further mocap fit options for this version only")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="speed-against-") as tmp:
        tmp = Path(tmp)
        earlier = tmp / "earlier"
        added = subprocess.run(["git", "worktree", "add", "--detach", "--quiet", str(earlier), args.rev], cwd=ROOT,
                               capture_output=True, text=True)
        if added.returncode:
            print(f"speed_against_version: error: {args.rev}: {added.stderr.strip() or 'no such version'}",
                  file=sys.stderr)
            return 2
        try:
            seq = args.sequence
            if seq is None:
                seq = tmp / "walk"
                mocap(ROOT, "synth", "--out", str(seq), "--frames", str(args.frames), "--step", "4", "--noise", "cheung",
                      "--quiet")
            versions = {"earlier": (earlier, []), "this": (ROOT, shlex.split(args.fit_args))}
            for name, (cwd, extra) in versions.items():
                mocap(cwd, "fit", str(seq), "--out", str(tmp / f"warm-{name}"), "--frames", str(WARM_UP_FRAMES),
                      "--init", "auto", "--quiet", *extra)
            runs = {name: [] for name in versions}
            for r in range(args.repeats):  # alternately, so that both meet the same background load
                for name, (cwd, extra) in versions.items():
                    runs[name].append(timed_fit(cwd, seq, tmp / f"{name}-{r}", args.frames, extra))
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(earlier)], cwd=ROOT, check=False)
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    result = {"earlier_version": args.rev, "this_version": head.strip() + ("+changes" if dirty else ""), "frames": args.frames, "fit_args": args.fit_args}
    for name, rows in runs.items():
        result[name] = {"runs_seconds_per_frame": [round(r["seconds_per_frame"], 4) for r in rows],
                        "best_seconds_per_frame": min(r["seconds_per_frame"] for r in rows),
                        "mean_joint_error_mm": rows[0]["mean_joint_error_mm"],
                        "max_joint_error_mm": rows[0]["max_joint_error_mm"]}
    result["speedup"] = result["earlier"]["best_seconds_per_frame"] / result["this"]["best_seconds_per_frame"]
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
