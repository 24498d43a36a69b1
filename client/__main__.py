"""``python -m client --connect tcp://HOST:5555`` (also ``mocap client ...``): run one limb worker.

Exits 0 after the server's SHUTDOWN or on SIGTERM/SIGINT (within a second), 2 on bad arguments,
3 when the server refuses its CURVE handshake (a key problem: retrying cannot help).
"""
from __future__ import annotations

import argparse
import logging
import signal
import sys

import zmq

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_REFUSED = 3


def build_parser() -> argparse.ArgumentParser:
    from client.worker import RECONNECT_MAX, RECONNECT_MIN
    from common.argtypes import OneLineParser, count, non_negative, seconds, zmq_address

    p = OneLineParser(prog="mocap client", description="Limb-fitting client of a mocap server.")
    p.add_argument("--connect", type=zmq_address, required=True, help="server address, e.g. tcp://HOST:5555")
    p.add_argument("--id", dest="client_id", default=None, help="name in the server's logs and timing "
                                                              "(default HOST-PID-TAG, TAG random)")
    p.add_argument("--curve-keys", default=None, metavar="DIR",
                   help="CURVE keys: DIR/client.key_secret and the server's DIR/server.key")
    p.add_argument("--reconnect-min", type=seconds, default=RECONNECT_MIN,
                   help=f"first reconnect delay, s (default {RECONNECT_MIN:g})")
    p.add_argument("--reconnect-max", type=seconds, default=RECONNECT_MAX,
                   help=f"longest reconnect delay, s (default {RECONNECT_MAX:g})")
    p.add_argument("-v", "--verbose", action="store_true", help="log every request")
    p.add_argument("-q", "--quiet", action="store_true", help="log warnings only")
    # for local clusters and fault tests; not part of the user interface
    p.add_argument("--exit-with-parent", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--test-stall", type=non_negative, default=0.0, help=argparse.SUPPRESS)
    p.add_argument("--test-stall-requests", type=count(1), default=1, help=argparse.SUPPRESS)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.reconnect_max < args.reconnect_min:
        parser.error(f"--reconnect-max {args.reconnect_max:g} is below --reconnect-min {args.reconnect_min:g}")
    level = logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    name = f"client {args.client_id}" if args.client_id else "client"
    logging.basicConfig(level=level, format=f"{name}: %(message)s")
    from common.body import load_body_model
    from common.objective import compile_kernels
    from client.worker import CurveKeys, Worker, refusal

    try:
        curve = CurveKeys.load(args.curve_keys) if args.curve_keys else None
    except (OSError, ValueError) as exc:
        print(f"mocap client: error: --curve-keys {args.curve_keys}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    compile_kernels()
    worker = Worker(load_body_model(), args.connect, args.client_id, curve=curve,
                    reconnect_min=args.reconnect_min, reconnect_max=args.reconnect_max,
                    exit_with_parent=args.exit_with_parent, stall_seconds=args.test_stall,
                    stall_requests=args.test_stall_requests if args.test_stall > 0 else 0)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: worker.stop())
    try:
        outcome = worker.run()
    except zmq.ZMQError as exc:
        print(f"mocap client: error: {args.connect}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if outcome == "refused":
        print(f"mocap client: error: {args.connect}: {refusal(curve)}", file=sys.stderr)
        return EXIT_REFUSED
    logging.getLogger("client").info("%s after %d chains", outcome, worker.solved)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
