"""What the server trusts, and how it checks: CURVE keys (``create_curve_keys``, the key
folder ``mocap keys`` makes), which addresses it may bind without them (``check_bind``), and
every client's result, scored again before it is used (``check_result``)."""
from __future__ import annotations

import ipaddress
import os
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import zmq
import zmq.auth

from common.body import CHAINS, LIMB_CHAINS
from common.errors import UserError
from common.fitting import (HOP_JOBS, REDETECT_ROUND, ChainResult, FitOptions, FrameData, _limb_centre_segments,
                            _stage_backends, full_energy, with_spine_prior)
from common.search import FIT_JOBS

LOOPBACK_NAMES = ("localhost",)

SECRET_KEY_MODE = 0o600  # secret key files: their owner alone reads them


def create_curve_keys(directory: Path, clients: tuple[str, ...] = ("client",)) -> Path:
    """Make a key folder: server pair, ``clients/NAME.key`` (the allow-list) and, for the first
    client name, ``client.key_secret``, the pair ``python -m client --curve-keys DIR`` loads.
    Secret key files are ``SECRET_KEY_MODE``: made in a private folder (mkdtemp's 0700), so
    no other user can open one between its creation and its chmod.

    Deployments give clients a copy without ``server.key_secret``.
    """
    directory = Path(directory)
    allowed = directory / "clients"
    allowed.mkdir(parents=True, exist_ok=True)
    private = Path(tempfile.mkdtemp(prefix=".keys-", dir=directory))
    try:
        pairs = [("server", *zmq.auth.create_certificates(private, "server"))]
        pairs += [(name, *zmq.auth.create_certificates(private, name)) for name in clients]
        for i, (name, public, secret) in enumerate(pairs):
            os.chmod(secret, SECRET_KEY_MODE)
            if name == "server":
                shutil.move(public, directory / "server.key")
                shutil.move(secret, directory / "server.key_secret")
                continue
            shutil.move(public, allowed / f"{name}.key")
            shutil.move(secret, directory / ("client.key_secret" if i == 1 else f"{name}.key_secret"))
    finally:
        shutil.rmtree(private, ignore_errors=True)
    return directory


def check_bind(bind: str, curve_keys: Path | None, insecure: bool) -> bool:
    """Without CURVE, only a loopback (127.0.0.0/8, ::1, localhost) or ipc/inproc address:
    anyone who reaches a network address could send poses. ``insecure`` allows it; returns
    whether it did (UserError where it is needed and not given)."""
    if curve_keys is not None:
        return False
    scheme, _, rest = bind.partition("://")
    if scheme in ("ipc", "inproc"):
        return False
    host = rest.rpartition(":")[0].strip("[]")
    try:
        local = host in LOOPBACK_NAMES or ipaddress.ip_address(host).is_loopback
    except ValueError:  # "*", an interface or a host name
        local = False
    if local:
        return False
    if not insecure:
        raise UserError(f"--bind {bind}: not a loopback address, and without --curve-keys any host that reaches "
                        f"it could join and send results; give --curve-keys DIR (mocap keys), a loopback --bind "
                        f"(tcp://127.0.0.1:5555), or --insecure on a network you trust")
    return True


def server_keys(directory: Path) -> tuple[bytes, bytes, Path]:
    directory = Path(directory)
    secret_file, allowed = directory / "server.key_secret", directory / "clients"
    try:
        public, secret = zmq.auth.load_certificate(secret_file)
    except (OSError, ValueError) as exc:
        raise UserError(f"--curve-keys {directory}: cannot read server.key_secret: {exc}") from None
    if secret is None:
        raise UserError(f"--curve-keys {directory}: server.key_secret holds no secret key")
    if not allowed.is_dir() or not any(allowed.glob("*.key")):
        raise UserError(f"--curve-keys {directory}: no allowed client keys in clients/*.key")
    return public, secret, allowed



# ----------------------------------------------------------------------------- results

def score_job(frame: FrameData, job: str, start: np.ndarray, params: np.ndarray, options: FitOptions,
              iteration: int) -> tuple[int, int | None]:
    """(energy_before, energy): what ``solve_job`` reports for ``job`` solved from ``start``
    to ``params`` (35,), one evaluation each, in the energy it was solved in. The XOR counts
    are integers and deterministic, so an honest result matches exactly. ``energy`` is None for
    a coarse-to-fine limb outside the re-detection round: its last (gl) stage places its windows
    at the first stage's result, which the message does not carry.

    The server dispatches limb chains, hops and whole fits only (torso and head it fits itself)."""
    if job in FIT_JOBS:
        return full_energy(frame.model, frame, start), full_energy(frame.model, frame, params)
    if job in HOP_JOBS:
        objective = with_spine_prior(frame.whole_image_energy(), options.spine_twist_prior)
        before, after = (round(float(objective(p[None])[0])) for p in (start, params))
        return before, after
    if job not in LIMB_CHAINS:
        raise ValueError(f"{job!r} is not a job the cluster dispatches")
    moving = CHAINS[job].segments
    if iteration == REDETECT_ROUND:  # ``redetect_limb``: the whole images, every stage the same energy
        setup = replace(frame.full_setup(start), moving=moving, prerender=True)
        energy = frame.energy("cpu" if options.energy == "coarse-to-fine" else options.energy, setup)
        return int(energy(start)[0]), int(energy(params)[0])
    backends = _stage_backends(options)
    setup = replace(frame.window_setup(start, _limb_centre_segments(job), options.limb_window_px, options.prerender),
                    moving=moving)
    energy = frame.energy(backends[0], setup)
    before = int(energy(start)[0])
    return before, (int(round(float(energy(params)[0]))) if len(backends) == 1 else None)


def check_result(frame: FrameData, result: ChainResult, start: np.ndarray, options: FitOptions,
                 iteration: int) -> str | None:
    """Why ``result`` of a job solved from ``start`` (35,) cannot be used, or None: its energies
    are not those of its parameters (``score_job``), or a limb's result moved parameters that
    are not its chain's (the solves hold them, so an honest result leaves them bit for bit)."""
    params = np.asarray(result.params, dtype=np.float64)
    if params.shape != start.shape or not np.all(np.isfinite(params)):
        return f"parameters of shape {params.shape}, not {start.shape} finite numbers"
    if result.chain in LIMB_CHAINS:
        others = np.ones(len(start), dtype=bool)
        others[list(CHAINS[result.chain].params)] = False
        if not np.array_equal(params[others], start[others]):
            return f"parameters outside {result.chain} moved"
    before, after = score_job(frame, result.chain, start, params, options, iteration)
    if before != result.energy_before or (after is not None and after != result.energy):
        return (f"claimed energies {result.energy_before} -> {result.energy}, its parameters score "
                f"{before} -> {after if after is not None else '?'}")
    return None
