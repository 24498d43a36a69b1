"""``mocap voxels``: SPOT voxel reconstruction of every frame of a sequence (Cheung et al. 2000).

Writes into OUT:
    voxels/<frame:06d>.npz    occupancy and surface voxels, packbits + grid metadata
                              (``common.voxels.save_voxels`` / ``load_voxels``), in the
                              user's world (``--up``): index [i, j, k] along its x, y, z
    pictures/<frame:06d>.png  the surface voxels as points from the front, the side and above
                              (the floor down, whatever the world's up axis)
    voxels.json               grid (bounds and voxel size in the user's world), its up axis,
                              per-frame counts and timing

The volume is carved in the fit frame (z up, ``common.world``); a world whose up axis is
another turns onto it by a signed permutation of the axes, so the grid is the same voxels in
the user's world, its axes permuted and flipped.
"""
from __future__ import annotations

import json
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from common.errors import InputFileError, UserError
from common.sequence import FRAME_NAME, load_sequence
from common.argtypes import count, real
from server.commands.fit import add_world_arguments
from server.output import add_overwrite_argument, add_units_argument, check_folder_target, staged_folder, write_text
from server.session import usable_cameras
from common.voxels import SpotGrid, bounds_around, save_voxels, silhouette_centre

SUMMARY = "voxels.json"
MAX_GRID = 256  # voxels per side: the lookup table takes about 110 bytes a voxel (1.8 GB at 256)
BOUNDS_SAMPLES = 30  # frames whose silhouettes' centres place the default box
PICTURE_SIZE = 240  # pixels per view
BACKGROUND = (24, 24, 28)
POINT_COLOUR = np.array([120.0, 190.0, 255.0])  # nearest points; farther ones are darker
DEPTH_DARKENING = 0.65  # fraction of brightness lost from the nearest to the farthest point
# (name, viewing direction, image-up direction); the actor faces -y in the rest pose.
VIEWS = (
    ("front", (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    ("side", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("top", (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
)


def register(subparsers) -> None:
    p = subparsers.add_parser("voxels", help="SPOT voxel reconstruction of a sequence's silhouettes",
                              description="Reconstruct the voxels of every frame from the silhouettes "
                                          "by SPOT (Cheung et al. 2000) and write them with pictures.")
    p.add_argument("sequence", type=Path, help="sequence folder (calibration.json + silhouettes/)")
    p.add_argument("--out", type=Path, required=True, help="result folder")
    p.add_argument("--grid", type=count(2, MAX_GRID), default=64,
                   help=f"voxels per side N of the N^3 grid (default 64, at most {MAX_GRID}: about 2 GB of memory)")
    p.add_argument("--q", type=count(1), default=2, help="sample pixels per voxel and camera (default 2)")
    p.add_argument("--epsilon", type=real(0.0, 1.0), default=None,
                   help="a voxel is inside a camera's silhouette with at least epsilon*Q samples (default 1/Q)")
    p.add_argument("--bounds", type=real(), nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="volume of interest in metres, in the calibration's world (default: 2.4 x 2.4 x 2.2 m "
                        "around the actor wherever the take's silhouettes put it, one box for all frames)")
    p.add_argument("--frames", type=count(1), default=None, help="only the first N frames")
    p.add_argument("--pictures", type=count(0), default=1, metavar="EVERY",
                   help="a picture every EVERY frames (0: none; default 1)")
    add_units_argument(p)
    add_world_arguments(p)
    add_overwrite_argument(p)
    p.add_argument("--quiet", action="store_true", help="print nothing")
    p.set_defaults(func=run)


def run(args) -> int:
    check_folder_target(args.out, (SUMMARY, "voxels", "pictures"), overwrite=args.overwrite, what="reconstruction")
    seq = load_sequence(args.sequence, args.units, up=args.up, mask_threshold=args.mask_threshold,
                        clean_masks=args.clean_masks, calibration=args.calibration)
    if not seq.has_silhouettes:
        raise InputFileError(seq.path / "silhouettes", "missing: make silhouettes first (mocap segment)")
    bounds = None if args.bounds is None else np.array(args.bounds).reshape(2, 3)
    if bounds is not None and not np.all(bounds[0] < bounds[1]):
        raise UserError(f"--bounds: expected X0 Y0 Z0 below X1 Y1 Z1, got {' '.join(f'{v:g}' for v in args.bounds)}")
    frames = seq.frames[:args.frames] if args.frames else seq.frames
    seq = usable_cameras(seq, frames)
    to_user = seq.world.rotation.T  # x_user = W^T x_fit
    if bounds is not None:  # the user's box, as the fit frame holds it
        bounds = np.sort(seq.world.points_to_fit(bounds), axis=0)
    else:  # around the actor wherever it goes (the studio's middle can miss it)
        sampled = frames[::max(1, -(-len(frames) // BOUNDS_SAMPLES))]
        bounds = bounds_around(seq.studio, [silhouette_centre(seq.studio, seq.silhouettes(f)) for f in sampled])
    start = time.perf_counter()
    grid = SpotGrid.build(seq.studio, grid=args.grid, q=args.q, bounds=bounds, epsilon=args.epsilon)
    build_seconds = time.perf_counter() - start
    rows = []
    # the voxels and their pictures of every frame, or the old ones as they were
    pictures = staged_folder(args.out / "pictures") if args.pictures else nullcontext()
    with staged_folder(args.out / "voxels") as voxel_dir, pictures as picture_dir:
        for i, frame in enumerate(frames):
            masks = seq.silhouettes(frame)
            t0 = time.perf_counter()
            result = grid.reconstruct(masks)
            seconds = time.perf_counter() - t0
            name = FRAME_NAME.format(frame=frame)
            save_voxels(voxel_dir / Path(name).with_suffix(".npz"), result.turned(to_user), frame=frame, q=grid.q,
                        threshold=grid.threshold, world_up=seq.world.up)
            if args.pictures and i % args.pictures == 0:
                Image.fromarray(picture(result.surface_points(), grid.bounds)).save(picture_dir / name)
            rows.append({"frame": int(frame), "occupied": int(result.occupied.sum()),
                         "surface": int(result.surface.sum()), "tests": result.tests, "seconds": seconds})
    median = float(np.median([r["seconds"] for r in rows]))
    summary = {
        "sequence": str(seq.path), "grid": grid.grid, "q": grid.q, "threshold": grid.threshold,
        "cameras": len(seq.studio), "world_up": seq.world.up,
        "bounds": np.sort(seq.world.points_to_user(grid.bounds), axis=0).tolist(),
        "voxel_size": np.abs(to_user @ grid.voxel_size).tolist(),
        "build_seconds": build_seconds, "frames_per_second": 1.0 / median if median > 0 else None,
        "frames": rows,
    }
    write_text(args.out / SUMMARY, json.dumps(summary, indent=1))
    if not args.quiet:
        fps = f"{summary['frames_per_second']:.0f}" if summary["frames_per_second"] else "-"
        print(f"  frames     {len(rows)}\n  grid       {grid.grid}^3, Q = {grid.q}, {len(seq.studio)} cameras\n"
              f"  voxels     {np.mean([r['occupied'] for r in rows]):.0f} occupied, "
              f"{np.mean([r['surface'] for r in rows]):.0f} surface (mean per frame)\n"
              f"  speed      {fps} frames/s (median, with surface; lookup table built in {build_seconds:.2f} s)\n"
              f"  written    {args.out}")
    return 0


def picture(points, bounds, size: int = PICTURE_SIZE) -> np.ndarray:
    """(n, 3) points inside bounds (2, 3) -> (size, len(VIEWS) * size, 3) uint8, orthographic views."""
    bounds = np.asarray(bounds, dtype=np.float64)
    centre = bounds.mean(axis=0)
    extent = float(np.max(bounds[1] - bounds[0]))
    views = []
    for name, forward, up in VIEWS:
        f, u = np.array(forward), np.array(up)
        axes = np.stack([np.cross(f, u), -u, f])  # image right, image down, depth
        img = np.empty((size, size, 3), dtype=np.uint8)
        img[:] = BACKGROUND
        if len(points):
            q = (np.asarray(points) - centre) @ axes.T
            _splat(img, (q[:, :2] / extent + 0.5) * size, q[:, 2])
        pil = Image.fromarray(img)
        ImageDraw.Draw(pil).text((4, 2), name, fill=(200, 200, 200))
        views.append(np.asarray(pil))
    return np.concatenate(views, axis=1)


def _splat(img: np.ndarray, uv: np.ndarray, depth: np.ndarray, radius: int = 1) -> None:
    """Draw points as small squares, nearest on top (a z-buffer by sorting)."""
    size = img.shape[0]
    span = depth.max() - depth.min()
    shade = 1.0 - DEPTH_DARKENING * ((depth - depth.min()) / span if span > 0 else 0.0)
    offsets = np.arange(-radius, radius + 1)
    du, dv = np.meshgrid(offsets, offsets)
    u = (np.rint(uv[:, 0])[:, None] + du.reshape(-1)).astype(np.int64).reshape(-1)
    v = (np.rint(uv[:, 1])[:, None] + dv.reshape(-1)).astype(np.int64).reshape(-1)
    d = np.repeat(depth, du.size)
    s = np.repeat(shade, du.size)
    ok = (u >= 0) & (u < size) & (v >= 0) & (v < size)
    pix = v[ok] * size + u[ok]
    order = np.lexsort((d[ok], pix))
    first = np.unique(pix[order], return_index=True)[1]
    chosen = order[first]
    flat = img.reshape(-1, 3)
    flat[pix[chosen]] = (POINT_COLOUR * s[ok][chosen, None]).astype(np.uint8)
