"""How many threads a process fits with: the cores it may use, ``--threads`` and
$MOCAP_THREADS, and the energies bound to one thread's GL context. Shared by the single
process (``server.session.LocalSolver``) and a cluster's server (``server.cluster``), which
solves short rounds on its own cores."""
from __future__ import annotations

import os

from common.errors import UserError
from common.fitting import FitOptions


def usable_cores() -> int:
    """The CPU cores this process may run on."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


# Threads of a single-process fit when not told (``--threads 0``): this variable where set (a
# batch's workers, one take per core, set it to 1), else every usable core.
THREADS_ENV = "MOCAP_THREADS"
# Backends whose energy is bound to one thread's GL context
SINGLE_THREAD_BACKENDS = ("gl", "coarse-to-fine")


def backend_threads(threads: int, options: FitOptions) -> int:
    """``threads`` (at least 1), or 1 for the backends bound to one GL context."""
    return 1 if options.energy in SINGLE_THREAD_BACKENDS else max(1, int(threads))


def resolve_threads(threads: int, options: FitOptions) -> int:
    """The threads a single-process fit runs: ``threads``, or where 0 $MOCAP_THREADS or every
    usable core; 1 for the GL backends."""
    if threads <= 0:
        value = os.environ.get(THREADS_ENV, "")
        try:
            threads = int(value) if value else usable_cores()
        except ValueError:
            raise UserError(f"${THREADS_ENV}: expected a whole number of threads, got {value!r}") from None
    return backend_threads(threads, options)
