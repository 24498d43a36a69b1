"""A project's takes and what each holds: the layouts a take may have, the takes below a
project's folder, the Config.toml files over a take, its recordings and its calibration.

A project is a folder with ``Config.toml`` at its root; a take is a folder below it holding
 - ``videos/<camera>.<ext>`` (or ``videos/<camera>/`` image folders) with
   ``background/<camera>.<ext>`` (or folders) of the empty studio: imported, then segmented;
 - or ``images/<camera>/`` and ``background/<camera>/``: imported the same way;
 - or a ready sequence (``sequence.json``, or ``silhouettes/`` without videos/ or images/): fitted as
   it is, at its own frame rate; segmented first where it has ``images/`` and no ``silhouettes/``;
 - or a lab's own layout, a folder per camera: ``<camera>/video.<ext>`` (or a ``video/`` image
   folder) with ``<camera>/background.<ext>``, and each camera's calibration file beside them
   (``<camera>/config.xml``) or at the take's top (``<camera>.xml``, a .qca.txt, a Pose2Sim
   .toml): imported like videos/, the take read as its calibration as ``mocap calib convert``
   reads it (the board description and notes beside them passed over; two calibrations refused);
plus a calibration (``[calibration] file``, else ``calibration.json``, ``calibration.toml``,
``Calib.toml``, a ``calibration/`` folder or EasyMocap's ``intri.yml`` + ``extri.yml``, in the
take and then in the project; two of them in one folder are refused, naming both).
"""
from __future__ import annotations

from pathlib import Path

from common.calibration import camera_files_in, camera_files_named, folder_calibrations
from common.errors import UserError
from common.sequence import IMAGE_SUFFIXES
from server.config import CONFIG_FILE, Config, load_config

CALIBRATION_NAMES = ("calibration.json", "calibration.toml", "Calib.toml", "calibration")
EASYMOCAP_FILES = ("intri.yml", "extri.yml")
SEQUENCE_MARKERS = ("sequence.json", "silhouettes")
SOURCE_FOLDERS = ("videos", "images")
CAMERA_FOLDER_STEMS = ("video", "background")  # a lab's own layout: <camera>/video.avi, <camera>/background.avi
# what a camera's folder's video.<ext> may be, besides images (a reference clip named video.json is not)
VIDEO_SUFFIXES = (".avi", ".mp4", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm", ".wmv", ".mts", ".m2ts", ".ts",
                  ".mxf", ".3gp", ".flv", ".ogv", ".mjpeg", ".y4m")
MIN_CAMERA_FOLDERS = 2  # with a video and a background each: fewer is a clip kept somewhere, not a studio
TAKE_LAYOUTS = ("videos/, images/, sequence.json, silhouettes/ or two camera folders or more with video.<ext> and "
                "background.<ext>")


def _holds_take_markers(folder: Path) -> bool:
    return any((folder / name).exists() for name in SOURCE_FOLDERS + SEQUENCE_MARKERS)


def is_take(folder: Path) -> bool:
    try:
        return folder.is_dir() and (_holds_take_markers(folder) or bool(_camera_folders(folder)))
    except OSError:  # a folder this user may not read is no take of theirs
        return False


def _is_recording(path: Path) -> bool:
    """A camera folder's video or image file, or its folder of images."""
    if path.name.startswith("."):
        return False
    if path.is_dir():
        return any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir())
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES + IMAGE_SUFFIXES


def video_folders(take: Path) -> dict[str, dict[str, list[Path]]]:
    """{camera: {stem: [its recordings so named]}} of the sub-folders holding a video recording
    (not a take's own: the sequence a run imports into the take; not one this user may not read)."""
    found = {}
    for sub in _sub_folders(take):
        try:
            if _holds_take_markers(sub):
                continue
            named = {stem: [p for p in sorted(sub.iterdir()) if p.stem.lower() == stem and _is_recording(p)]
                     for stem in CAMERA_FOLDER_STEMS}
        except OSError:
            continue
        if named[CAMERA_FOLDER_STEMS[0]]:
            found[sub.name] = named
    return found


def _camera_folders(take: Path) -> dict[str, dict[str, list[Path]]]:
    """``video_folders`` of a take laid out a folder per camera: where at least
    MIN_CAMERA_FOLDERS of them hold an empty-studio recording too (clips named video.mp4 kept
    here and there make no take of a project's folder); else {}."""
    found = video_folders(take)
    whole = sum(all(named.values()) for named in found.values())
    return found if whole >= MIN_CAMERA_FOLDERS else {}


def camera_folder_sources(take: Path) -> tuple[dict[str, Path], dict[str, Path]]:
    """({camera: recording}, {camera: empty-studio recording}) of a take laid out a folder per
    camera (``<camera>/video.<ext>`` or ``<camera>/video/`` of images, ``<camera>/background.<ext>``);
    a camera's folder is one holding a recording, so the sequence a run imports into the take is
    none. Two recordings of one kind in one camera's folder are refused, naming them."""
    found: tuple[dict[str, Path], dict[str, Path]] = ({}, {})
    for camera, named in _camera_folders(take).items():
        for (stem, paths), sources in zip(named.items(), found):
            if len(paths) > 1:
                raise UserError(f"{take / camera}: holds {len(paths)} {stem} recordings: "
                                f"{', '.join(p.name for p in paths)}; keep one")
            if paths:
                sources[camera] = paths[0]
    return found


def find_takes(project: Path) -> list[Path]:
    """The takes of a project folder (at any depth, not inside another take), sorted; a take
    given as the project is the one take."""
    project = Path(project)
    if not project.is_dir():
        raise UserError(f"{project}: not a folder")
    return takes_below(project)


def takes_below(folder: Path) -> list[Path]:
    if is_take(folder):
        return [folder]
    return [t for sub in _sub_folders(folder) for t in takes_below(sub)]


def _sub_folders(folder: Path) -> list[Path]:
    return [sub for sub in sorted(folder.iterdir()) if sub.is_dir() and not sub.name.startswith(".")]


def folders_without_takes(project: Path) -> list[Path]:
    """The project's folders (the highest of each branch) that hold no take, but for its
    calibration folder: a take whose recordings' folder is misspelt (``video/``) or empty."""
    out = []
    for sub in _sub_folders(Path(project)) if not is_take(Path(project)) else []:
        if sub.name in CALIBRATION_NAMES:
            continue
        out += [sub] if not takes_below(sub) else folders_without_takes(sub)
    return out


def project_of(take: Path) -> Path | None:
    """The nearest folder above the take that holds a Config.toml (the project), or None."""
    for folder in Path(take).resolve().parents:
        if (folder / CONFIG_FILE).is_file():
            return folder
    return None


def config_files(take: Path) -> list[Path]:
    """The Config.toml files that apply to a take: the project's, then the take's own."""
    take = Path(take).resolve()
    project = project_of(take)
    return ([project / CONFIG_FILE] if project else []) + [take / CONFIG_FILE]


def take_config(take: Path) -> Config:
    return load_config(config_files(take))


def find_calibration(take: Path, config: Config, cameras: list[str] | None = None) -> Path:
    """The calibration of a take: [calibration] file, else one in the take, else one in the
    project. A take laid out a folder per camera (``cameras``: its cameras' folders; None: another
    layout) is read as ``mocap calib convert TAKE`` reads it: a calibration file at its top by any
    name (a .qca.txt, a Pose2Sim .toml), camera files at its top named by camera, or the camera
    files in its cameras' folders."""
    given = config.get("calibration", "file")
    if given:
        if not Path(given).exists():
            raise UserError(f"[calibration] file {given} (from {config.source('calibration', 'file')}): missing")
        return Path(given)
    project = project_of(take)
    for folder in [take] + ([project] if project else []):  # a take's own calibration before the project's
        if folder == take and cameras is not None:
            found = _per_camera_calibrations(take, cameras)
        else:
            found = [(folder / name, name) for name in CALIBRATION_NAMES if (folder / name).exists()]
            if all((folder / name).is_file() for name in EASYMOCAP_FILES):
                found.append((folder, " + ".join(EASYMOCAP_FILES)))
        if len(found) > 1:  # two in one folder: which was meant (or last edited) is not ours to guess
            raise UserError(f"{folder}: holds {len(found)} calibrations: {', '.join(name for _, name in found)}; "
                            "keep one, or set [calibration] file")
        if found:
            return found[0][0]
    per_camera = ", calibration or camera files at its top or in its cameras' folders" if cameras is not None else ""
    raise UserError(f"{take}: no calibration (looked for {', '.join(CALIBRATION_NAMES)} and intri.yml + extri.yml "
                    f"in the take and the project{per_camera}; or set [calibration] file)")


def _per_camera_calibrations(take: Path, cameras: list[str]) -> list[tuple[Path, str]]:
    """(what to read, its name) of each calibration in a take laid out a folder per camera, as
    ``mocap calib convert TAKE`` finds them: the single-file ones and EasyMocap's at its top
    (``folder_calibrations``), a calibration/ folder, and its camera files at its top or in its
    cameras' folders (``take_camera_files``)."""
    found = [(path, what) for kind, path, what in folder_calibrations(take) if kind != "camera"]
    found += [(take / name, name) for name in CALIBRATION_NAMES if (take / name).is_dir()]
    return found + [(take, camera_files_named(take, files)) for files in take_camera_files(take, cameras) if files]


def take_camera_files(take: Path, cameras: list[str]) -> tuple[list[Path], list[Path]]:
    """The camera files (K, R, t or P) at the top of a take laid out a folder per camera, and
    those in its cameras' folders (never in its other folders: a calibration/ folder is one
    calibration, not a camera)."""
    return camera_files_in(take), [f for camera in cameras for f in camera_files_in(take / camera)]


def named_sources(folder: Path) -> dict[str, Path]:
    """{camera: path} of a videos/ or background/ folder: files by stem, folders by name."""
    if not folder.is_dir():
        return {}
    return {(p.stem if p.is_file() else p.name): p for p in sorted(folder.iterdir()) if not p.name.startswith(".")}


def holds_calibration(sequence: Path) -> bool:
    """Whether a sequence folder holds its own calibration (calibration.json, or EasyMocap's two files)."""
    return (sequence / "calibration.json").is_file() or all((sequence / n).is_file() for n in EASYMOCAP_FILES)


def shown_names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))
