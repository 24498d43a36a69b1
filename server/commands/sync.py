"""``mocap sync``: which frames the cameras took together, from a sequence's silhouettes.

Cameras without a shared clock, or a video that lost its first frames, leave camera c's frame
i showing the moment of the others' frame i + d. This command estimates every camera's d
(``common.sync.estimate_offsets``) and prints the ``mocap import-video --offset`` that puts
the frames together. It reads the silhouettes as they are (the multi-view cleaning assumes the
cameras in step) and writes nothing.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from common.argtypes import count
from common.errors import InputFileError, UserError
from common.sequence import load_sequence
from common.sync import MAX_OFFSET, SYNC_FRAMES, estimate_offsets, judged_frames
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
    seq = load_sequence(args.sequence, args.units, up=args.up, mask_threshold=args.mask_threshold, clean_masks=False)
    if not seq.has_silhouettes:
        raise InputFileError(seq.path / "silhouettes", "missing: make silhouettes first (mocap segment)")
    if len(seq.studio) < 3:
        raise UserError(f"{seq.path}: {len(seq.studio)} cameras: a camera is judged against the visual hull of "
                        f"at least two others")
    frames = seq.frames
    spacing = frame_spacing(frames)
    count = (frames[-1] - frames[0]) // spacing + 1  # indices on the frames' grid, missing ones too
    try:
        judged_frames(count, args.max_offset, args.frames)
    except ValueError as exc:
        raise UserError(f"{seq.path}: {exc} (--max-offset)") from None
    present = set(frames)
    cache: dict[tuple[int, int], np.ndarray] = {}

    def mask_of(k: int, i: int) -> np.ndarray | None:
        frame = frames[0] + i * spacing
        if frame not in present or not 0 <= i < count:
            return None
        if (k, frame) not in cache:
            cache[k, frame] = seq.mask(seq.studio[k], frame)
        return cache[k, frame]

    estimate = estimate_offsets(seq.studio, mask_of, count, args.max_offset, args.frames)
    # a camera that cannot tell and was never moved has no offset to give
    offsets = {c.camera: c.offset * spacing if c.resolved or c.offset else None for c in estimate.cameras}
    if args.json:
        print(json.dumps({"offsets": offsets, "unresolved": estimate.unresolved, "frame_spacing": spacing,
                          "frames_judged": [frames[0] + i * spacing for i in estimate.frames],
                          "agreement": {c.camera: {str(d * spacing): round(s, 4) for d, s in c.scores.items()}
                                        for c in estimate.cameras}}, indent=1))
        return 0
    width = max(len(c.camera) for c in estimate.cameras)
    for c in estimate.cameras:
        if offsets[c.camera] is None:
            print(f"{c.camera:<{width}}   ?  cannot tell: no offset fits clearly better than its neighbours (the actor "
                  f"moves little across this view, so its offset also matters little to a fit)")
            continue
        at_zero = f" (at 0: {c.scores[0]:.3f})" if c.offset and 0 in c.scores else ""
        sharp = "" if c.resolved else ", not sharply: its neighbours fit almost as well"
        print(f"{c.camera:<{width}}  {offsets[c.camera]:+d}  agreement {c.scores[c.offset]:.3f}{at_zero}{sharp}")
    sharp = {c.camera: offsets[c.camera] for c in estimate.cameras if c.resolved and c.offset}
    blurred = {c.camera: offsets[c.camera] for c in estimate.cameras if not c.resolved and c.offset}
    if sharp:
        print("import again with: --offset " + " ".join(f"{n}={o}" for n, o in sharp.items())
              + " (added to any --offset the import was given)")
    if blurred:
        print("not sharp, check by eye before using: " + " ".join(f"{n}={o}" for n, o in blurred.items()))
    if not sharp and not blurred:
        told = [c.camera for c in estimate.cameras if c.resolved]
        if not told:
            print("no camera's offset could be told: the actor hardly moves in these frames")
        else:
            print("the cameras are in step" + (f" (as far as {', '.join(told)} can tell)"
                                               if len(told) < len(estimate.cameras) else ""))
    if spacing > 1:
        print(f"(frames are {spacing} apart: offsets are found to {spacing} frames; import every frame of a stretch "
              f"with --step 1 for single frames)")
    return 0
