"""``mocap run TAKE``: every step of a take, from its raw files to exports and report.html.

Steps that are done (their outputs made from the same inputs and settings, and all there) are
skipped; outputs edited by hand since are kept as edited, said in one line, and the steps that
read them run again. An output in the way of a step that runs, that no run made or one changed
since, is refused unless ``--overwrite``; see ``server.project``. Settings come from the
project's and the take's Config.toml. Each step that runs says why (``why_it_runs``), the
warnings it prints are said under it, and the log of every command's output is named
(``--json``: per step a ``warnings`` list and, where it ran, its ``why``; and ``log``).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from common.argtypes import one_line
from common.errors import UserError
from server.output import counted, shell_word
from server.project import TakeFailed, run_take


def register(sub) -> None:
    p = sub.add_parser("run", help="every step of a take (import, segment, fit, export, report) as its "
                                   "Config.toml says; steps already up to date are skipped")
    p.add_argument("take", type=Path, help="take folder (videos/, images/, a sequence, or a folder per camera "
                   "holding video.<ext> and background.<ext>; in a project)")
    p.add_argument("--overwrite", action="store_true",
                   help="where a step runs, replace outputs that mocap run did not make, or that changed since "
                        "it made them (default: refuse the take, so that nothing is lost; outputs edited by "
                        "hand of a step whose settings and inputs did not change are kept either way)")
    p.add_argument("--json", action="store_true", help="print what was done as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    def progress(step: str, state: str) -> None:
        if not args.json:
            print(f"  {step}: {state}", file=sys.stderr, flush=True)

    try:
        done = run_take(args.take, progress, overwrite=args.overwrite)
    except UserError as exc:  # the error's one line is the command's last; its whole output is in the log
        failed = isinstance(exc, TakeFailed)
        if failed:
            progress(exc.steps[-1]["step"], f"full log: {exc.log}")
        if args.json:  # a script reading stdout gets JSON either way (the error line goes to stderr too)
            print(json.dumps({"name": args.take.name, "path": str(args.take), "status": "failed",
                              "error": one_line(str(exc)),
                              **({"steps": exc.steps, "log": str(exc.log)} if failed else {})}, indent=1))
        raise
    if args.json:
        print(json.dumps(done, indent=1))
    else:
        for step in done["steps"]:
            if "note" in step:  # outputs edited by hand, kept and used
                print(f"{done['name']}: {step['step']}: {step['note']}")
        print(f"{done['name']}: {done['status']} -> {done['result']}")
        if "mean_xor_share" in done:  # what a take without truth is checked by (mocap fit's table)
            from server.session import xor_sides  # here: the fitting modules load only where a take has a fit

            reported = any(step["step"] == "report" for step in done["steps"])  # [report] enabled = false: none
            print(f"  {counted(done['frames'], 'frame')}, actor size {done.get('actor_scale', 1.0):.2f} x the body model, "
                  f"XOR {done['mean_xor_share']:.0%} of the silhouettes"
                  + (f" once the {done['cleared_share']:.0%} no fitted pose explains was cleared"
                     + (f" ({done['xor_share_before_clearing']:.0%} of the masks before it)"
                        if "xor_share_before_clearing" in done else "")
                     if "cleared_share" in done else "") + ", "
                  f"{counted(done.get('frames_flagged', 0), 'frame')} flagged"
                  + (" (report.html)" if reported else f" (mocap report {shell_word(done['result'])})"))
            if "mean_missed_share" in done:  # a line of its own: the sides carry a note in brackets
                print(f"  of the XOR: {xor_sides(done)}")
        if any(step["warnings"] for step in done["steps"]):  # said under their steps, above
            print(f"  full log: {done['log']}")
    return 0
