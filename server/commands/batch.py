"""``mocap batch PROJECT``: every take of a project, one per worker, on Dask distributed."""
from __future__ import annotations

import json
from pathlib import Path

from common.argtypes import count
from server.batch import BATCH_FILE, INDEX_FILE, run_batch, summary_table

EXIT_SOME_FAILED = 1


def register(sub) -> None:
    p = sub.add_parser("batch", help="every take of a project (mocap run each), on a local or remote Dask cluster",
                       description="Run every take of a project folder, one take per worker. Takes already done "
                                   "are skipped, interrupted ones continue; a take that fails is reported and the "
                                   "others go on. Writes PROJECT/batch.json and PROJECT/index.html.")
    p.add_argument("project", type=Path, help="project folder (Config.toml and takes below it)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=count(1), default=None,
                       help="local worker processes (default: one per core)")
    where.add_argument("--scheduler", default=None, metavar="tcp://HOST:8786",
                       help="run on this existing Dask cluster (workers started with `dask worker`)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace outputs that mocap run did not make, or that changed since it made them "
                        "(default: such a take is refused and reported)")
    p.add_argument("--quiet", action="store_true", help="no progress, no table")
    p.add_argument("--json", action="store_true", help="print batch.json")
    p.set_defaults(func=run)


def run(args) -> int:
    record = run_batch(args.project, workers=args.workers, scheduler=args.scheduler, quiet=args.quiet or args.json,
                       overwrite=args.overwrite)
    if args.json:
        print(json.dumps(record, indent=1))
    elif not args.quiet:
        print("\n".join(summary_table(record)))
        print(f"written {Path(record['project']) / BATCH_FILE}")
        print(f"written {Path(record['project']) / INDEX_FILE} (every take's report linked)")
    return EXIT_SOME_FAILED if any(t["status"] == "failed" for t in record["takes"]) else 0
