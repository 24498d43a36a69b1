"""Pure math shared by the server and the clients: arrays in, arrays out.

numba caches each compiled function beside its source and checks only that one file, while our
kernels call across files (``energy.pose_energies`` -> ``body``; ``powell_cpu`` -> ``energy``,
``body`` and ``optimize``'s constants): an edit to one would leave the others' cached machine
code stale. So the cache lives in a folder named by a hash of every kernel source, unless
NUMBA_CACHE_DIR is set (the Docker image sets it and compiles into it when it is built).
"""
from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

# files whose kernels numba caches
KERNEL_SOURCES = ("blobs.py", "body.py", "conic_bits.py", "consistency.py", "energy.py", "ellipsoid_fit.py", "optimize.py", "powell_cpu.py")


def _kernel_cache_dir() -> str | None:
    """The cache folder for these sources, created; None where it cannot be (a read-only
    install: numba then keeps its own per-user cache)."""
    here = Path(__file__).parent
    digest = hashlib.sha256(b"".join((here / name).read_bytes() for name in KERNEL_SOURCES)).hexdigest()[:16]
    folder = here / "__pycache__" / f"numba-{digest}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    return str(folder) if os.access(folder, os.W_OK) else None


if "NUMBA_CACHE_DIR" not in os.environ and (_folder := _kernel_cache_dir()) is not None:
    os.environ["NUMBA_CACHE_DIR"] = _folder  # inherited by client processes
    if "numba" in sys.modules:  # imported before us: it has read its settings already
        from numba.core import config

        config.CACHE_DIR = _folder
