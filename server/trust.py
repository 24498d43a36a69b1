"""What the server trusts, and how it checks: CURVE keys (``create_curve_keys``, the key
folder ``mocap keys`` makes), which addresses it may bind without them (``check_bind``), and
every client's result, scored again before it is used (``check_result``)."""
from __future__ import annotations

import ipaddress
import os
import re
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import zmq
import zmq.auth

from common.body import CHAINS, LIMB_CHAINS
from common.energy import whole_energy
from common.errors import UserError
from common.fitting import (EVOLVE_JOBS, HOP_JOBS, REDETECT_ROUND, ChainResult, FitOptions, FrameData, _limb_centre_segments,
                            _stage_backends, full_energy, whole_body_objective)
from common.search import FIT_JOBS
from server.output import shell_word

LOOPBACK_NAMES = ("localhost",)
# mocap server's --bind when none is given: every interface only where CURVE keeps strangers out;
# without keys the one address check_bind allows, so that the default always starts
NETWORK_BIND = "tcp://*:5555"
LOOPBACK_BIND = "tcp://127.0.0.1:5555"

SECRET_KEY_MODE = 0o600  # secret key files: their owner alone reads them


CLIENT_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")  # a file name on any system
RESERVED_CLIENT_NAMES = ("server",)  # the server's own pair is made beside the clients' ones
CLIENT_FOLDER = "for-{name}"  # one client's folder: its pair as client.key_secret, and server.key


def check_client_names(names: tuple[str, ...]) -> None:
    """UserError naming the first client name that is empty, repeated, reserved or not a plain
    file name (letters, digits, '_', '.', '-')."""
    seen = set()
    for name in names:
        if not name:
            raise UserError("--clients: an empty name (two commas, or one at an end)")
        if not CLIENT_NAME.fullmatch(name):
            raise UserError(f"--clients: {name!r}: a client name is letters, digits, '_', '.' and '-' "
                            "(up to 64, not starting with '.' or '-')")
        if name in RESERVED_CLIENT_NAMES:
            raise UserError(f"--clients: {name!r} is the server's own key's name; choose another")
        if name in seen:
            raise UserError(f"--clients: {name!r} given twice: each client needs a key of its own")
        seen.add(name)


def create_curve_keys(directory: Path, clients: tuple[str, ...] = ("client",)) -> Path:
    """Make a key folder: the server's pair, ``clients/NAME.key`` (the allow-list) and, per
    client, ``for-NAME/`` holding its pair as ``client.key_secret`` and the server's public
    ``server.key``: the folder ``mocap client --curve-keys DIR`` loads, to copy to that client's
    machine. The first client's pair is also ``client.key_secret`` at the top, so that the
    folder itself serves a client on the server's machine.
    Secret key files are ``SECRET_KEY_MODE``: made in a private folder (mkdtemp's 0700), so
    no other user can open one between its creation and its chmod.
    """
    check_client_names(clients)
    directory = Path(directory)
    allowed = directory / "clients"
    allowed.mkdir(parents=True, exist_ok=True)
    private = Path(tempfile.mkdtemp(prefix=".keys-", dir=directory))
    try:
        public, secret = zmq.auth.create_certificates(private, "server")
        os.chmod(secret, SECRET_KEY_MODE)
        shutil.move(public, directory / "server.key")
        shutil.move(secret, directory / "server.key_secret")
        for i, name in enumerate(clients):
            public, secret = zmq.auth.create_certificates(private, name)
            os.chmod(secret, SECRET_KEY_MODE)
            own = directory / CLIENT_FOLDER.format(name=name)
            own.mkdir()
            shutil.copyfile(directory / "server.key", own / "server.key")
            if i == 0:  # copied in the private folder, so that the copy too is never readable by others
                shutil.copy2(secret, private / "first.key_secret")
                shutil.move(private / "first.key_secret", directory / "client.key_secret")
            shutil.move(public, allowed / f"{name}.key")
            shutil.move(secret, own / "client.key_secret")
    finally:
        shutil.rmtree(private, ignore_errors=True)
    return directory


def default_bind(curve_keys: Path | None) -> str:
    return LOOPBACK_BIND if curve_keys is None else NETWORK_BIND


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
    if not secret_file.is_file():  # zmq would say only "Invalid certificate file"
        if (directory / "client.key_secret").is_file():
            raise UserError(f"--curve-keys {directory}: a client's key folder (no server.key_secret); give the "
                            "server the folder mocap keys made")
        if directory.is_dir() and any(directory.glob("*.key")):  # the allow-list mocap keys made inside
            raise UserError(f"--curve-keys {directory}: holds client keys but no server.key_secret: the clients/ "
                            f"allow-list? Give the folder mocap keys made ({shell_word(directory.parent)}, if so)")
        if directory.is_file():
            raise UserError(f"--curve-keys {directory}: is a file; give the folder mocap keys made")
        where = "no such folder" if not directory.is_dir() else f"{secret_file} is missing"
        raise UserError(f"--curve-keys {directory}: {where}; make the keys with: mocap keys {shell_word(directory)}")
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
    are deterministic (their weights dyadic), so an honest result matches exactly. ``energy`` is None for
    a coarse-to-fine limb outside the re-detection round: its last (gl) stage places its windows
    at the first stage's result, which the message does not carry.

    The server dispatches limb chains, hops, evolutions and whole fits only (torso and head it fits itself)."""
    if job in FIT_JOBS:
        return full_energy(frame.model, frame, start), full_energy(frame.model, frame, params)
    if job in HOP_JOBS or job in EVOLVE_JOBS:  # both on the same objective
        objective = whole_body_objective(frame, options)
        before, after = (whole_energy(objective(p[None])[0]) for p in (start, params))
        return before, after
    if job not in LIMB_CHAINS:
        raise ValueError(f"{job!r} is not a job the cluster dispatches")
    moving = CHAINS[job].segments
    if iteration == REDETECT_ROUND:  # ``redetect_limb``: the whole images, every stage the same energy
        setup = replace(frame.full_setup(start), moving=moving, prerender=True)
        energy = frame.energy("cpu" if options.energy == "coarse-to-fine" else options.energy, setup)
        return whole_energy(energy(start)[0]), whole_energy(energy(params)[0])
    backends = _stage_backends(options)
    setup = replace(frame.window_setup(start, _limb_centre_segments(job), options.limb_window_px, options.prerender),
                    moving=moving)
    energy = frame.energy(backends[0], setup)
    before = whole_energy(energy(start)[0])
    return before, (whole_energy(energy(params)[0]) if len(backends) == 1 else None)


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
