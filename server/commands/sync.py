"""``mocap sync``: which frames the cameras took together, from a sequence's silhouettes.

Cameras without a shared clock, or a video that lost its first frames, leave camera c's frame
i + d_c showing the moment of the others' frame i. This command estimates every camera's d_c
(``common.sync.estimate_offsets``) and prints the ``mocap import-video --offset`` that puts
the frames together: d_c added to the offset the sequence was imported with. It reads the
silhouettes as they are (the multi-view cleaning assumes the cameras in step) and writes nothing.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common.argtypes import count
from common.errors import InputFileError, UserError
from common.sequence import load_sequence
from common.sync import MAX_OFFSET, SYNC_FRAMES, SyncEstimate, estimate_offsets, judged_frames
from server.commands.fit import add_world_arguments
from server.output import add_units_argument


def register(subparsers) -> None:
    p = subparsers.add_parser("sync", help="estimate the cameras' frame offsets from the silhouettes",
                              description="Estimate each camera's frame offset from a sequence's silhouettes (the "
                                          "frames where the other cameras' visual hull fits its silhouette best) "
                                          "and print the mocap import-video --offset that puts them in step. "
                                          "Writes nothing.")
    p.add_argument("sequence", type=Path, help="sequence folder (calibration.json + silhouettes/), every frame "
                                               "imported (--step 1) for single-frame offsets")
    p.add_argument("--max-offset", type=count(1, 100), default=MAX_OFFSET, metavar="N",
                   help=f"offsets tried either way, in the sequence's frames (default {MAX_OFFSET})")
    p.add_argument("--frames", type=count(2, 1000), default=SYNC_FRAMES, metavar="N",
                   help=f"frames judged, evenly across the take (default {SYNC_FRAMES})")
    add_units_argument(p)
    add_world_arguments(p, clean=False)
    p.add_argument("--json", action="store_true", help="print the estimate as JSON")
    p.set_defaults(func=run)


def frame_spacing(frames: list[int]) -> int:
    """The step of the sequence's frame numbers: their differences' greatest common divisor (a
    ``--step 10`` import: 10, with frames some camera lacked left out)."""
    return int(np.gcd.reduce(np.diff(frames))) if len(frames) > 1 else 1


def run(args) -> int:
    seq = load_sequence(args.sequence, args.units, up=args.up, mask_threshold=args.mask_threshold, clean_masks=False,
                        calibration=args.calibration)
    if not seq.has_silhouettes:
        raise InputFileError(seq.path / "silhouettes", "missing: make silhouettes first (mocap segment)")
    if len(seq.studio) < 3:
        raise UserError(f"{seq.path}: {len(seq.studio)} cameras: a camera is judged against the visual hull of "
                        f"at least two others")
    frames = seq.frames
    spacing = frame_spacing(frames)
    indices = (frames[-1] - frames[0]) // spacing + 1  # on the frames' grid, missing ones too
    try:
        judged_frames(indices, args.max_offset, args.frames)
    except ValueError as exc:
        raise UserError(f"{seq.path}: {exc} (--max-offset)") from None
    present = set(frames)
    cache: dict[tuple[int, int], tuple] = {}  # packed bits: a long take's frames near those judged

    def mask_of(k: int, i: int) -> np.ndarray | None:
        frame = frames[0] + i * spacing
        if frame not in present or not 0 <= i < indices:
            return None
        if (k, frame) not in cache:
            mask = seq.mask(seq.studio[k], frame)
            cache[k, frame] = (np.packbits(mask), mask.shape)
        bits, shape = cache[k, frame]
        return np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape).astype(bool)

    estimate = estimate_offsets(seq.studio, mask_of, indices, args.max_offset, args.frames)
    imported = {n: int(o) for n, o in seq.meta.get("offsets", {}).items()}
    if args.json:
        print(json.dumps(report(estimate, spacing, imported, frames[0]), indent=1))
        return 0
    for line in report_lines(estimate, spacing, imported, args.max_offset, args.frames):
        print(line)
    return 0


MIN_TELLING = 3  # cameras that must tell their offset sharply before one is named: with two, which moved is unknown


def offsets_found(estimate: SyncEstimate, spacing: int) -> dict:
    """{camera: its offset in source frames, or None where it cannot tell and was never moved}."""
    return {c.camera: c.offset * spacing if c.resolved or c.offset else None for c in estimate.cameras}


def report(estimate: SyncEstimate, spacing: int, imported: dict, first: int) -> dict:
    """``--json``'s document."""
    found = offsets_found(estimate, spacing)
    return {"offsets": found, "unresolved": estimate.unresolved, "frame_spacing": spacing,
            "import_offsets": {n: imported.get(n, 0) + o for n, o in found.items() if o is not None},
            "cameras_telling": sum(c.resolved for c in estimate.cameras),
            "frames_tried": [first + i * spacing for i in estimate.frames],
            "frames_judged": {c.camera: c.judged for c in estimate.cameras},
            "agreement": {c.camera: {str(d * spacing): round(s, 4) for d, s in c.scores.items()}
                          for c in estimate.cameras}}


def report_lines(estimate: SyncEstimate, spacing: int, imported: dict, max_offset: int,
                 frames_asked: int = SYNC_FRAMES) -> list[str]:
    """What ``mocap sync`` prints: a line per camera, then what to do (``frames_asked``: the
    frames the take was to be judged on, more than it had room for in a short take)."""
    found = offsets_found(estimate, spacing)
    telling = sum(c.resolved for c in estimate.cameras)
    width = max(len(c.camera) for c in estimate.cameras)
    lines = []
    for c in estimate.cameras:
        name = f"{c.camera:<{width}}"
        if c.judged < 2:
            lines.append(f"{name}   ?  no frame to judge: a frame within {max_offset} of each one tried is missing "
                         f"(a smaller --max-offset, or fewer frames left out at import)")
        elif found[c.camera] is None:
            lines.append(f"{name}   ?  cannot tell: no offset fits clearly better than its neighbours (the actor "
                         f"moves little across this view, so its offset also matters little to a fit)")
        else:
            at_zero = f" (at 0: {c.scores[0]:.3f})" if c.offset and 0 in c.scores else ""
            why = ""
            if not c.resolved:
                why = (f", at the end of the offsets tried: try a larger --max-offset" if abs(c.offset) >= max_offset
                       else ", not sharply: its neighbours fit almost as well")
            lines.append(f"{name}  {found[c.camera]:+d}  agreement {c.scores[c.offset]:.3f}{at_zero}{why}")
    sharp = {c.camera for c in estimate.cameras if c.resolved and c.offset}
    blurred = {c.camera for c in estimate.cameras if not c.resolved and c.offset}
    if sharp and telling < MIN_TELLING:  # two cameras apart: either may be the one off
        blurred, sharp = blurred | sharp, set()
        lines.append(f"only {telling} cameras tell their offset: which of them is out of step cannot be told")

    def total(names):  # the import's --offset: what it was given and what was found
        return " ".join(f"{n}={imported.get(n, 0) + found[n]}" for n in found if n in names)
    if sharp:
        kept = [n for n, o in imported.items() if o and n not in sharp]
        lines.append("import again with: --offset " + total(sharp)
                     + "".join(f" {n}={imported[n]}" for n in kept))
    if blurred:
        lines.append("not sharp, check by eye before using: --offset " + total(blurred))
    if not sharp and not blurred:
        told = [c.camera for c in estimate.cameras if c.resolved]
        every_camera_judged = all(c.judged >= 2 for c in estimate.cameras)
        if not told and every_camera_judged and len(estimate.frames) < frames_asked:
            lines.append(f"no camera's offset could be told: only {len(estimate.frames)} frames could be judged "
                         f"(of --frames {frames_asked}; a take needs {2 * max_offset} frames at each end beyond "
                         f"those judged): a longer stretch of the take would tell more")
        elif not told:
            lines.append("no camera's offset could be told"
                         + (": the actor hardly moves in these frames" if every_camera_judged else ""))
        else:
            lines.append("the cameras are in step" + (f" (as far as {', '.join(told)} can tell)"
                                                      if len(told) < len(estimate.cameras) else ""))
    if spacing > 1:
        lines.append(f"(frames are {spacing} apart: offsets are found to {spacing} frames; import every frame of a "
                     f"stretch with --step 1 for single frames)")
    return lines
