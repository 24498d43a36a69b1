"""``mocap segment``: colour images + empty-studio frames -> binary silhouettes.

Reads the colour images (``images/<camera>/``) and the empty-studio frames
(``background/<camera>/``, one or many per camera) of a sequence folder, in any format
``common.sequence`` reads, and writes ``silhouettes/<camera>/<frame:06d>.png``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from common.errors import InputFileError
from common.segmentation import METHODS, load_params, make_segmenter, params_dict
from common.sequence import (IMAGE_SUFFIXES, MASK_FOLDERS, check_size, frame_files, image_size, load_sequence, read_image,
                             write_mask_png, write_sequence_meta)
from server.output import (add_calibration_argument, add_overwrite_argument, check_folder_target, counted,
                           staged_folder, write_text)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "segment", help="background subtraction: images/ and background/ -> silhouettes/",
        description="Segment the colour images of a sequence folder into silhouettes by background "
                    "subtraction (Cheung et al. 2000 or Bottino & Laurentini), per camera, against "
                    "the empty-studio frames in background/<camera>/.")
    parser.add_argument("sequence", help="sequence folder with calibration.json, images/ and background/")
    parser.add_argument("--method", choices=sorted(METHODS), default="cheung",
                        help="background subtraction method (default: cheung)")
    parser.add_argument("--params", metavar="FILE.toml",
                        help="method parameters as flat TOML keys over the defaults")
    add_calibration_argument(parser)
    add_overwrite_argument(parser)
    parser.set_defaults(func=run)


def _read_rgb(path: Path, camera) -> np.ndarray:
    image = read_image(path, "RGB")
    check_size(image.shape, path, camera)
    return image


def run(args) -> int:
    params = load_params(args.method, args.params)
    seq = load_sequence(args.sequence, calibration=args.calibration)
    root = seq.path
    # Check every folder and file before writing anything.
    background_files = {}
    for cam in seq.studio:
        bg_dir = root / "background" / cam.name
        if not bg_dir.is_dir():
            raise InputFileError(bg_dir, f"missing: empty-studio frames of camera {cam.name} are needed "
                                         "(background/<camera>/<n:06d>.png)")
        files = list(frame_files(bg_dir).values())
        if not files:
            raise InputFileError(bg_dir, f"no numbered empty-studio images ({', '.join(IMAGE_SUFFIXES)})")
        background_files[cam.name] = files
        for path in files:  # the size from the header; the pixels are read once, below
            width, height = image_size(path)
            check_size((height, width), path, cam)
    seq.check_files(seq.frames, masks=False, images=True)
    silhouettes = root / MASK_FOLDERS[0]
    # the sequence's own silhouettes/: no option writes them elsewhere
    check_folder_target(silhouettes, ("*",), option=None, overwrite=args.overwrite, what="segmentation", given=False)

    seconds = 0.0
    with staged_folder(silhouettes) as staged:  # all new silhouettes, or the old ones as they were
        for cam in seq.studio:
            backgrounds = np.stack([_read_rgb(p, cam) for p in background_files[cam.name]])
            segmenter = make_segmenter(args.method, params).fit(backgrounds)
            for frame in seq.frames:
                image = seq.image(cam, frame)
                t0 = time.perf_counter()
                mask = segmenter.segment(image)
                seconds += time.perf_counter() - t0
                write_mask_png(staged / seq.silhouette_path(cam.name, frame).relative_to(silhouettes), mask)

    record = {"method": args.method, "params": params_dict(params)}
    meta_path = root / "sequence.json"
    if meta_path.exists():
        doc = dict(seq.meta)
        doc["segmentation"] = record
        write_text(meta_path, json.dumps(doc, indent=1))
    else:
        write_sequence_meta(root, seq.frames, seq.fps, seq.studio.names, segmentation=record)
    count = len(seq.frames) * len(seq.studio)
    print(f"segmented {counted(len(seq.frames), 'frame')} x {counted(len(seq.studio), 'camera')} with {args.method} "
          f"({count / max(seconds, 1e-9):.0f} images/s) -> {root / 'silhouettes'}")
    return 0
