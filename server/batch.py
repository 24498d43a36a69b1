"""``mocap batch``: every take of a project, one per worker, on Dask distributed.

Takes are independent, so each is one Dask task (``run_take_task``: ``mocap run`` in the
worker's process). By default a local cluster of one single-threaded worker process per core
is started (and stopped); ``scheduler`` runs on an existing cluster (``dask scheduler`` and
``dask worker`` started elsewhere: SSH, Slurm, containers). What Dask gives: a lost worker's
take is run again elsewhere (up to ``distributed.scheduler.allowed-failures`` times), and the
take's fit then continues from the frames already written. What this module adds: one progress
line over the batch, each take's line with the warnings its steps printed, a failed take
reported with its error while the others go on, and at the end ``PROJECT/batch.json`` and
``PROJECT/index.html``.
"""
from __future__ import annotations

import html
import json
import logging
import os
import sys
import time
from pathlib import Path

from common.errors import UserError, print_warning
from server.output import counted, write_text
from server.project import TakeFailed, frames_done, run_take
from server.takes import TAKE_LAYOUTS, find_takes, folders_without_takes
from server.threads import THREADS_ENV, usable_cores

BATCH_FILE = "batch.json"
INDEX_FILE = "index.html"
POLL_SECONDS = 1.0  # how often the progress line is brought up to date
SHUTDOWN_SECONDS = 10.0  # for the client and the local cluster to close
# one thread per worker, and one for the numerical libraries in it: the takes are the parallelism
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
              THREADS_ENV: "1"}  # one take per core: each fit runs one thread


def run_take_task(take: str, overwrite: bool = False) -> dict:
    """A take on a worker: what ``run_take`` returns, or ``status: failed`` with the one-line error.

    Bad input is the take's own failure (reported, the batch goes on); anything else is said in
    one line too, so that one broken take never stops the others. A take that failed in a step
    keeps the steps run until then (their warnings) and names its log.
    """
    try:
        return run_take(Path(take), overwrite=overwrite)
    except TakeFailed as exc:
        return {"name": Path(take).name, "path": take, "status": "failed", "error": str(exc), "steps": exc.steps,
                "log": str(exc.log)}
    except UserError as exc:
        return {"name": Path(take).name, "path": take, "status": "failed", "error": str(exc)}
    except Exception as exc:  # a bug must not hide the other takes' results
        return {"name": Path(take).name, "path": take, "status": "failed", "error": f"{type(exc).__name__}: {exc}"}


def start_client(workers: int | None, scheduler: str | None):
    """(dask Client, LocalCluster or None): on ``scheduler``, else on a new local cluster."""
    os.environ.update(WORKER_ENV)  # inherited by the local worker processes
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout=30), None
        except OSError as exc:
            raise UserError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
    cluster = LocalCluster(n_workers=workers or usable_cores(), threads_per_worker=1, processes=True,
                           host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR)
    return Client(cluster), cluster


def run_batch(project: Path, workers: int | None = None, scheduler: str | None = None, quiet: bool = False,
              started=None, overwrite: bool = False) -> dict:
    """Run every take of ``project``; writes and returns the batch record (``batch.json``).

    ``started``: called with the Dask client once the takes are submitted (tests kill a worker).
    ``overwrite``: as ``mocap run --overwrite`` for every take.
    """
    project = Path(project).resolve()
    takes = find_takes(project)
    if not takes:
        raise UserError(f"{project}: no takes (folders with {TAKE_LAYOUTS})")
    others = folders_without_takes(project)
    if others and not quiet:
        print_warning(f"{project}: skipped, no take in them (no {TAKE_LAYOUTS}): "
                      + ", ".join(p.relative_to(project).as_posix() for p in others))
    t0 = time.perf_counter()
    client, cluster = start_client(workers, scheduler)
    try:
        from distributed import wait

        n_workers = len(client.scheduler_info().get("workers", {}))
        futures = {client.submit(run_take_task, str(t), overwrite, key=f"take-{i}-{t.name}", pure=False): t
                   for i, t in enumerate(takes)}
        if started:
            started(client)
        pending, results = set(futures), {}
        while pending:
            try:
                done, pending = wait(pending, timeout=POLL_SECONDS, return_when="FIRST_COMPLETED")
            except TimeoutError:  # nothing finished in this interval: only the progress line moves
                done = set()
            for future in done:
                take = futures[future]
                try:
                    results[take] = future.result()
                except Exception as exc:  # the take's worker died too often (KilledWorker), or similar
                    results[take] = {"name": take.name, "path": str(take), "status": "failed",
                                     "error": f"{type(exc).__name__}: {exc}"}
                if not quiet:
                    _clear_line()
                    print("\n".join([take_line(results[take]), *warning_lines(results[take])]), flush=True)
            if not quiet:
                _progress_line(takes, results, time.perf_counter() - t0)
    finally:
        _close(client, cluster)
    if not quiet:
        _clear_line()
    rows = [results[t] | {"error": results[t].get("error")} for t in takes]
    record = {"project": str(project), "scheduler": scheduler or "local", "workers": n_workers,
              "seconds": time.perf_counter() - t0, "takes": rows}
    write_text(project / BATCH_FILE, json.dumps(record, indent=1))
    write_text(project / INDEX_FILE, index_html(record))
    return record


def _close(client, cluster) -> None:
    """Client first, then the local cluster; the results are in, so a slow or noisy shutdown
    (workers still heart-beating a closed scheduler) is not the batch's failure."""
    import distributed

    quiet = logging.getLogger("distributed")
    level, quiet.level = quiet.level, logging.CRITICAL
    try:
        client.close(timeout=SHUTDOWN_SECONDS)
        if cluster is not None:
            cluster.close(timeout=SHUTDOWN_SECONDS)
    except (OSError, distributed.comm.CommClosedError):
        pass
    finally:
        quiet.level = level


def take_line(row: dict) -> str:
    if row["status"] == "failed":
        return f"  {row['name']}: failed: {row['error']}"
    figures = ""
    if row.get("frames"):
        figures = f", {counted(row['frames'], 'frame')}"
        if row.get("seconds_per_frame"):
            figures += f", {row['seconds_per_frame']:.2f} s/frame"
    kept = "".join(f"; {s['step']}: {s['note']}" for s in row.get("steps", ()) if "note" in s)
    return f"  {row['name']}: {row['status']}{figures}{kept}"


def warning_lines(row: dict) -> list[str]:
    """The warnings a take's steps printed (what mocap run shows under each step), each named by
    the take, and where its whole log is when there were some or a step failed."""
    lines = [f"  {row['name']}: {s['step']}: warning: {w}" for s in row.get("steps", ()) for w in s.get("warnings", ())]
    if (lines or row["status"] == "failed") and row.get("log"):
        lines.append(f"  {row['name']}: full log: {row['log']}")
    return lines


def _progress_line(takes: list[Path], results: dict, elapsed: float) -> None:
    if not sys.stderr.isatty():
        return
    counts = [frames_done(t) for t in takes]
    done = sum(d for d, _ in counts)
    total = sum(n or d for d, n in counts)
    rate = done / elapsed if elapsed > 0 else 0.0
    eta = f"{(total - done) / rate:.0f} s" if rate > 0 else "-"
    sys.stderr.write(f"\rbatch: {len(results)}/{len(takes)} takes, {done}/{total} frames, {rate:.2f} frames/s, "
                     f"ETA {eta}   ")
    sys.stderr.flush()


def _clear_line() -> None:
    if sys.stderr.isatty():
        sys.stderr.write("\r\033[K")


def quality_cell(take: dict) -> str:
    """A take's fit quality as the tables say it: 'XOR% (outside%)', the mean XOR share of the
    silhouettes and its side of the body outside them (a wrong pose shows there; foreground no
    body covers, a prop, only in the XOR), and the share of the masks that no fitted pose explains,
    cleared before it; '' before a fit."""
    if "mean_xor_share" not in take:
        return ""
    outside = f" ({take['mean_outside_share']:.0%})" if "mean_outside_share" in take else ""
    cleared = f", {take['cleared_share']:.0%} cleared" if "cleared_share" in take else ""
    return f"{take['mean_xor_share']:.0%}{outside}{cleared}"


def summary_table(record: dict) -> list[str]:
    """One row per take: frames, s/frame, fit quality, accuracy where there is truth, status."""
    rows = [("take", "frames", "s/frame", "XOR (outside)", "mean/max mm", "status")]
    for t in record["takes"]:
        acc = (f"{t['mean_joint_error_mm']:.1f}/{t['max_joint_error_mm']:.1f}" if "mean_joint_error_mm" in t else "-")
        spf = f"{t['seconds_per_frame']:.2f}" if t.get("seconds_per_frame") else "-"
        status = t["status"] + (f": {t['error']}" if t.get("error") else "")
        rows.append((t["name"], str(t.get("frames", "-")), spf, quality_cell(t) or "-", acc, status))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    return ["  " + "  ".join(r[i].ljust(widths[i]) for i in range(5)) + "  " + r[5] for r in rows]


def index_html(record: dict) -> str:
    """PROJECT/index.html: the table, each take linked to its report."""
    project = Path(record["project"])
    body = []
    for t in record["takes"]:
        report = Path(t.get("result", "")) / "report.html"
        name = html.escape(t["name"])
        if t["status"] != "failed" and report.is_file():
            name = f'<a href="{html.escape(os.path.relpath(report, project))}">{name}</a>'
        acc = (f"{t['mean_joint_error_mm']:.1f} / {t['max_joint_error_mm']:.1f}" if "mean_joint_error_mm" in t else "")
        spf = f"{t['seconds_per_frame']:.2f}" if t.get("seconds_per_frame") else ""
        body.append(f"<tr><td>{name}</td><td>{t.get('frames', '')}</td><td>{spf}</td><td>{quality_cell(t)}</td>"
                    f"<td>{acc}</td>"
                    f"<td>{html.escape(t['status'])}</td><td>{html.escape(t.get('error') or '')}</td></tr>")
    return ("<!doctype html><meta charset='utf-8'><title>mocap batch</title>"
            "<style>body{font:14px sans-serif;margin:2em}td,th{padding:4px 10px;text-align:left}"
            "tr:nth-child(even){background:#f3f3f3}</style>"
            f"<h1>{html.escape(project.name)}</h1><p>{len(record['takes'])} takes on {record['workers']} workers "
            f"({html.escape(record['scheduler'])}), {record['seconds']:.0f} s</p><table><tr><th>take</th>"
            "<th>frames</th><th>s/frame</th><th>XOR of the silhouettes (body outside them)</th>"
            "<th>mean / max joint error, mm</th><th>status</th><th>error</th></tr>"
            + "".join(body) + "</table>")
