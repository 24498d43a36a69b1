"""``mocap demo``: the main job on the bundled data, end to end (see ``server.demo``)."""
from __future__ import annotations

from server.demo import add_demo_arguments, run_demo


def register(sub) -> None:
    p = sub.add_parser("demo", help="synthesise the bundled CMU walk in a virtual studio, fit it, write a report")
    add_demo_arguments(p)
    p.set_defaults(func=run_demo)
