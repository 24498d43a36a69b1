"""mocap synth: render a virtual-studio sequence from a BVH clip."""
from __future__ import annotations

import json
from pathlib import Path

from common.body import load_body_model
from common.errors import InputFileError, UserError
from common.synth import NOISE_MODELS, SURFACES, SynthOptions, synth_studio, synthesize
from server.progress import Progress

DEFAULT_CLIP = Path(__file__).resolve().parents[2] / "common" / "data" / "clips" / "cmu_12_01_walk.bvh"
DEFAULT_SIZE = "320x240"
MAX_STUDIO_M = 100.0  # metres, the largest --radius and --height taken


def parse_size(text: str, flag: str = "--size") -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"{flag}: expected WIDTHxHEIGHT such as 320x240, got {text!r}") from None
    if w < 16 or h < 16 or w > 4096 or h > 4096:
        raise UserError(f"{flag}: {w}x{h} outside 16..4096")
    return w, h


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """'WxH,WxH,...' -> [(w, h), ...], one per camera (cycled when fewer than cameras)."""
    return [parse_size(item.strip(), "--sizes") for item in text.split(",")]


def register(sub) -> None:
    p = sub.add_parser("synth", help="render a virtual-studio sequence from a BVH clip")
    p.add_argument("--clip", type=Path, default=DEFAULT_CLIP, help="BVH motion (default: a bundled CMU walk)")
    p.add_argument("--out", type=Path, required=True, help="sequence folder to write")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--start", type=int, default=1, help="first source frame (CMU frame 0 is a T-pose)")
    p.add_argument("--step", type=int, default=4, help="take every STEP-th source frame (120 fps -> 30 fps: 4)")
    p.add_argument("--cameras", type=int, default=8)
    sizes = p.add_mutually_exclusive_group()
    sizes.add_argument("--size", default=None, help=f"every camera's image size (default {DEFAULT_SIZE})")
    sizes.add_argument("--sizes", default=None, metavar="WxH,WxH,...",
                       help="image size per camera, cycled when fewer than cameras (a mixed-resolution studio)")
    p.add_argument("--radius", type=float, default=3.0, help="studio radius: cameras' distance from its axis, metres")
    p.add_argument("--height", type=float, default=1.5, help="height of the ring cameras, metres")
    p.add_argument("--noise", choices=NOISE_MODELS, default="none")
    p.add_argument("--surface", choices=SURFACES, default="skinned")
    p.add_argument("--images", action="store_true", help="also render colour images and empty backgrounds")
    p.add_argument("--joint-map", type=Path, default=None, help="TOML joint-name overrides for the clip")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    if not args.clip.exists():
        raise InputFileError(args.clip, "missing")
    if args.frames < 1 or args.step < 1 or args.start < 0:
        raise UserError("--frames and --step must be >= 1 and --start >= 0")
    if not 1 <= args.cameras <= 64:
        raise UserError("--cameras must be between 1 and 64")
    if not 0.0 < args.radius <= MAX_STUDIO_M:  # NaN too
        raise UserError(f"--radius: expected 0 < metres <= {MAX_STUDIO_M:g}, got {args.radius}")
    if not 0.0 <= args.height <= MAX_STUDIO_M:
        raise UserError(f"--height: expected 0 <= metres <= {MAX_STUDIO_M:g}, got {args.height}")
    sizes = parse_sizes(args.sizes) if args.sizes is not None else [parse_size(args.size or DEFAULT_SIZE)]
    if len(sizes) > args.cameras:
        raise UserError(f"--sizes: {len(sizes)} sizes for {args.cameras} cameras")
    studio = synth_studio(args.cameras, sizes, args.radius, args.height)
    opts = SynthOptions(frames=args.frames, start=args.start, step=args.step, noise=args.noise,
                        surface=args.surface, seed=args.seed, images=args.images)
    bar = Progress("synth", args.frames, enabled=None if not args.quiet else False)
    summary = synthesize(load_body_model(), studio, args.clip, args.out, opts, args.joint_map, bar)
    if not args.quiet:
        print(json.dumps({k: summary[k] for k in ("frames", "fps", "cameras", "noise", "surface")}))
    return 0
