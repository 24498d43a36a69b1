"""Output files and folders that never lose a result.

Every command that writes follows the same rules:
 - ``check_target`` runs before any work: ``--out`` naming a file where a folder goes (or the
   reverse), a folder that cannot be written, or an earlier result in the way (refused unless
   ``--resume`` or ``--overwrite``) is one clear error, and nothing is touched;
 - files are written beside their final name and renamed over it (``replace_file``,
   ``write_text``), so a crash leaves the old file or the new one, never half of one;
 - a folder made in one go (``mocap synth``, ``import-video``, ``voxels``) is built beside its
   final name and swapped in whole at the end (``staged_folder``): a failed run leaves the old
   folder as it was, and no old frames stay beside new ones.
"""
from __future__ import annotations

import os
import shlex
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from common.errors import UserError

OVERWRITE_HELP = "replace an earlier result there (default: refuse, so that nothing is lost)"


def add_overwrite_argument(p) -> None:
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


def add_calibration_argument(p) -> None:
    """--calibration: a calibration file for a sequence that holds none (segment and every
    command of ``add_world_arguments``)."""
    p.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                   help="the calibration to use, in any format mocap calib reads (default: the sequence's own "
                        "calibration.json, or intri.yml + extri.yml)")


def add_units_argument(p) -> None:
    """--units: the units of a calibration file that does not say (calib, import-video, fit,
    server, voxels, live)."""
    from common.calibration import UNIT_SCALE

    p.add_argument("--units", choices=sorted(UNIT_SCALE), default=None,
                   help="units of translations in calibration files that do not say (default: metres, checked)")


def shell_word(path) -> str:
    """``path`` as one word of a command to copy (quoted where it holds spaces or quotes)."""
    return shlex.quote(str(path))


SHOWN_NUMBERS = 5  # numbers a message lists before "and N more"


def listed(numbers) -> str:
    """"3, 8, 13" or "3, 8, 13, 18, 23 and 4 more": frame numbers for a message."""
    numbers = list(numbers)
    shown = ", ".join(str(n) for n in numbers[:SHOWN_NUMBERS])
    return shown + (f" and {len(numbers) - SHOWN_NUMBERS} more" if len(numbers) > SHOWN_NUMBERS else "")


def counted(n: int, noun: str) -> str:
    """"1 client", "4 clients": a count with its noun (plural by an s)."""
    return f"{n} {noun}{'' if n == 1 else 's'}"


def next_steps(*commands: str) -> str:
    """The line a command ends with: what to run next, so that a new user sees the way on."""
    return "next: " + "; ".join(commands)


def _named(path: Path, option: str | None, given: bool) -> str:
    """How an error names a target: with the option the user gave it by ("--out r/x.bvh"), or
    alone where it is the command's default, which no option the user typed named."""
    return f"{option} {path}" if given and option else str(path)


def _writable_folder(folder: Path, where: str) -> None:
    """The folder, or the nearest folder above it that exists, can be written to."""
    probe = folder
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise UserError(f"{where}: {probe} is a file, not a folder")
    _probe_write(probe, where)


def _probe_write(folder: Path, where: str) -> None:
    """Create and remove a file in ``folder``: the only test that read-only mounts, full disks
    and permissions (root ignores modes) all answer truthfully."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-test-"):
            pass
    except OSError as exc:
        raise UserError(f"{where}: {folder} is not writable ({exc.strerror or exc})") from None


def check_folder_target(folder: Path, earlier: tuple[str, ...], option: str | None = "--out", resume: bool = False,
                        overwrite: bool = False, what: str = "result", given: bool = True,
                        instead: str | None = None) -> bool:
    """Check a folder a command is about to write before any work is done.

    ``earlier``: names of files or folders whose presence means the folder holds an earlier
    result (``("*",)``: anything at all). Returns whether such a result is there (which
    ``resume`` or ``overwrite`` then allowed). Raises UserError naming the folder otherwise.
    ``option`` sets the folder (None: no option does, and no way elsewhere is offered);
    ``given``: whether the user gave it (else the folder is the command's default, named alone,
    and ``option`` is offered as the way elsewhere); ``instead``: another way out to offer.
    """
    folder = Path(folder)
    where = _named(folder, option, given)
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{where}: is a file; name a folder")
    _writable_folder(folder, where)
    if not folder.is_dir():
        return False
    present = sorted(p.name for p in folder.iterdir()) if earlier == ("*",) else \
        [name for name in earlier if (folder / name).exists()]
    if present and not (resume or overwrite):
        shown = ", ".join(present[:4]) + (", ..." if len(present) > 4 else "")
        again = "--resume to continue it or " if what == "result" else ""
        elsewhere = ("" if option is None else ", or choose another folder" if given
                     else f", or {option} to write elsewhere") + (f", or {instead}" if instead else "")
        raise UserError(f"{where}: holds an earlier {what} ({shown}); pass {again}--overwrite to replace it"
                        f"{elsewhere}")
    return bool(present)


def check_file_target(path: Path, overwrite: bool, option: str = "--out", given: bool = True) -> None:
    """A file a command is about to write: its folder exists and is writable, and an existing file
    there is replaced only with ``overwrite``. ``option``, ``given``: as for ``check_folder_target``."""
    path = Path(path)
    where = _named(path, option, given)
    if path.is_dir():
        raise UserError(f"{where}: is a folder; name a file")
    if not path.parent.is_dir():
        raise UserError(f"{where}: folder {path.parent} does not exist")
    _probe_write(path.parent, where)
    if path.exists() and not overwrite:
        elsewhere = "" if given else f", or {option} to write elsewhere"
        raise UserError(f"{where}: exists; pass --overwrite to replace it{elsewhere}")


def _partial_name(path: Path) -> Path:
    """A hidden name beside ``path`` with its suffix kept (writers that read the suffix)."""
    return path.with_name(f".{path.stem}.partial-{os.getpid()}{path.suffix}")


def replace_file(path: Path, write: Callable[[Path], None]) -> Path:
    """``write(tmp)`` a file beside ``path``, then rename it over ``path`` (atomic on one file
    system); the partial file is removed when ``write`` fails."""
    path = Path(path)
    tmp = _partial_name(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text(path: Path, text: str) -> Path:
    """``path.write_text(text)``, atomically."""
    return replace_file(path, lambda tmp: tmp.write_text(text))


@contextmanager
def staged_folder(folder: Path, merge: bool = False) -> Iterator[Path]:
    """Build a folder beside ``folder`` and swap it in when the block ends without an error.

    The block writes into the yielded path; an earlier ``folder`` (already allowed by
    ``check_folder_target``) is replaced whole, or with ``merge`` only the entries the block
    wrote are (the folder's other files stay). On an error the staged folder is removed and
    ``folder`` is as it was.
    """
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    staged = Path(tempfile.mkdtemp(prefix=f".{folder.name}.partial-", dir=folder.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(staged, 0o777 & ~umask)  # mkdtemp's 0700 would hide the folder from others (containers)
    try:
        yield staged
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        raise
    if merge and folder.is_dir():
        for entry in sorted(staged.iterdir()):
            _replace_entry(entry, folder / entry.name)
        staged.rmdir()
    else:
        _replace_entry(staged, folder)


def _replace_entry(new: Path, target: Path) -> None:
    """Rename ``new`` over ``target`` (a file or a folder); an old folder is moved aside first,
    as a rename cannot replace a folder that is not empty."""
    if not target.is_dir():
        os.replace(new, target)
        return
    aside = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
    os.replace(target, aside / target.name)
    os.replace(new, target)
    shutil.rmtree(aside, ignore_errors=True)
