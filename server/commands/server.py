"""mocap server: fit a sequence with limb clients connecting over ZeroMQ (``mocap client``).

Writes the same result folder as ``mocap fit``. On SIGTERM it stops within seconds, keeping
the frames already written (continue with ``--resume``) and leaving the clients to reconnect
to the next server; at the end of a run it tells the clients to exit. A network address needs
``--curve-keys`` (or ``--insecure``): see docs/cluster.md.
"""
from __future__ import annotations

import logging
import sys

from common.argtypes import count
from common.body import load_body_model
from server.cluster import ClusterSolver
from server.local_cluster import Terminated, add_cluster_arguments, terminate_on_sigterm
from server.trust import check_bind, default_bind, server_keys
from server.commands.fit import (actor_model, add_fit_arguments, check_resume_or_overwrite, finish,
                                 open_sequence_to_fit, options_from_args, schedules_from_args, warn_if_software_gl)
from server.output import check_folder_target
from server.progress import Progress
from server.results import RESULT_FILES, stopped_note
from server.session import run_fit

EXIT_TERMINATED = 143  # 128 + SIGTERM


def register(sub) -> None:
    p = sub.add_parser("server", help="fit a sequence with limb clients over the network")
    add_fit_arguments(p)
    p.add_argument("--threads", type=count(0), default=0,
                   help="the server's own threads: for the actor-size search and the rounds it keeps (default 0: "
                        "every core, or $MOCAP_THREADS); the poses are the same for any number")
    add_cluster_arguments(p, server=True)
    p.set_defaults(func=run)


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="mocap server: %(message)s")
    check_resume_or_overwrite(args)
    args.bind = default_bind(args.curve_keys) if args.bind is None else args.bind
    check_bind(args.bind, args.curve_keys, args.insecure)  # before the slow loading
    if args.curve_keys is not None:
        server_keys(args.curve_keys)  # a missing or wrong key folder, also before it
    # the folder first: a result in the way is refused before the slow actor-size search
    check_folder_target(args.out, RESULT_FILES, resume=args.resume, overwrite=args.overwrite)
    warn_if_software_gl(args.energy)
    seq = open_sequence_to_fit(args)
    options = options_from_args(args)
    schedules = schedules_from_args(args, options)
    init = args.init or ("truth" if seq.truth() else "auto")
    with terminate_on_sigterm():
        # bound first, so that clients (and a container's health check) find the server while
        # it sizes the actor
        solver = ClusterSolver(options, bind=args.bind, heartbeat_interval=args.heartbeat,
                               client_timeout=args.client_timeout, curve_keys=args.curve_keys,
                               insecure=args.insecure, threads=args.threads)
        shutdown = None
        try:
            # the actor's size as mocap fit chooses it, on the server's threads; the FRAMEs carry it
            # to the clients
            model, size = actor_model(load_body_model(), seq, options, args, init, args.threads, schedules)
            if args.min_clients > 0:
                logging.getLogger("server.cluster").info("waiting for %d client(s) on %s", args.min_clients,
                                                         solver.endpoint)
                solver.wait_for_clients(args.min_clients)
            bar = Progress("fit", min(len(seq.frames), args.frames or len(seq.frames)),
                           enabled=None if not args.quiet else False)
            summary = run_fit(model, seq, args.out, options, solver, init=args.init, resume=args.resume,
                              max_frames=args.frames, progress=bar, overwrite=args.overwrite, actor_size=size,
                              schedules=schedules)
            finish(model, seq, args, summary)  # results on disk before the clients are released
            shutdown = "run finished"
        except Terminated:
            print(f"mocap server: terminated; {stopped_note(args.out)}", file=sys.stderr)
            return EXIT_TERMINATED
        finally:
            solver.close(shutdown=shutdown)
    return 0
