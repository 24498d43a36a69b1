"""mocap synth: render a virtual-studio sequence from a BVH clip or a generated posture take.

Real-like studio options (defaults: the plain studio): ``--up`` writes the calibration and the
truth joints in a world with another up axis (the images are those of the z-up studio),
``--distortion K1`` gives every camera strong barrel distortion (k2 = -0.3 K1), ``--fov`` narrows
or widens the ring cameras, ``--prop chair|box`` adds a static prop the body model cannot
explain, ``--posture`` replaces the clip with a seeded take of a seated, crouching, kneeling or
lying actor at ``--position``.
"""
from __future__ import annotations

import json
from pathlib import Path

from common.body import load_body_model
from common.errors import InputFileError, UserError
from common.postures import POSTURES
from common.synth import (MAX_DISTORTION_K1, NOISE_MODELS, PROPS, RING_FOV_DEG, SURFACES, UP_AXES, SynthOptions,
                          synth_studio, synthesize)
from common.argtypes import count, real
from server.output import add_overwrite_argument, check_folder_target, next_steps, shell_word, staged_folder
from server.progress import Progress

DEFAULT_CLIP = Path(__file__).resolve().parents[2] / "common" / "data" / "clips" / "cmu_12_01_walk.bvh"
DEFAULT_SIZE = "320x240"
MAX_STUDIO_M = 100.0  # metres, the largest --radius and --height taken
FOV_RANGE_DEG = (10.0, 120.0)  # degrees, the --fov taken


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


def parse_position(text: str) -> tuple[float, float]:
    """'X,Y' metres -> (x, y), within MAX_STUDIO_M of the studio's centre."""
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise UserError(f"--position: expected X,Y in metres such as 0.5,-0.2, got {text!r}") from None
    if not (abs(x) <= MAX_STUDIO_M and abs(y) <= MAX_STUDIO_M):  # NaN too
        raise UserError(f"--position: {text!r} outside +-{MAX_STUDIO_M:g} m")
    return x, y


def register(sub) -> None:
    p = sub.add_parser("synth", help="render a virtual-studio sequence from a BVH clip or a posture")
    # choices checked in run(), not by argparse, so that a bad value is one error line
    p.add_argument("--clip", type=Path, default=None, help="BVH motion (default: a bundled CMU walk)")
    p.add_argument("--posture", default=None, metavar="|".join(POSTURES),
                   help="instead of a clip: a take moving smoothly between seeded variations of this posture "
                        "(--frames frames at 30 fps; --start, --step and --joint-map are for clips)")
    p.add_argument("--out", type=Path, required=True, help="sequence folder to write")
    p.add_argument("--frames", type=count(1), default=60,
                   help="frames to write (default 60; fewer where the clip ends first)")
    p.add_argument("--start", type=count(0), default=1,
                   help="first source frame (default 1: CMU frame 0 is a T-pose)")
    p.add_argument("--step", type=count(1), default=4,
                   help="take every STEP-th source frame (default 4: 120 fps -> 30 fps)")
    p.add_argument("--cameras", type=count(1), default=8,
                   help="cameras, 1 to 64 (default 8): a ring around the actor, from 5 on one of them overhead")
    sizes = p.add_mutually_exclusive_group()
    sizes.add_argument("--size", default=None, help=f"every camera's image size (default {DEFAULT_SIZE})")
    sizes.add_argument("--sizes", default=None, metavar="WxH,WxH,...",
                       help="image size per camera, cycled when fewer than cameras (a mixed-resolution studio)")
    p.add_argument("--radius", type=real(), default=3.0,
                   help="studio radius: cameras' distance from its axis, metres (default 3)")
    p.add_argument("--height", type=real(), default=1.5, help="height of the ring cameras, metres (default 1.5)")
    p.add_argument("--fov", type=real(), default=RING_FOV_DEG, metavar="DEG",
                   help=f"vertical field of view of the ring cameras, degrees (default {RING_FOV_DEG:g})")
    p.add_argument("--distortion", type=real(), default=0.0, metavar="K1",
                   help="radial distortion k1 of every camera (barrel < 0, e.g. -0.35), with k2 = -0.3 K1")
    p.add_argument("--up", default="+z", metavar="|".join(UP_AXES),
                   help="up axis of the world calibration.json and the truth joints are written in (default +z; "
                        "write --up=-z); the images are the z-up studio's")
    p.add_argument("--prop", default=None, metavar="|".join(PROPS),
                   help="a static prop: a chair under the actor's pelvis or a box beside the actor")
    p.add_argument("--position", default="0,0", metavar="X,Y",
                   help="the actor's floor position in the z-up studio, metres (default 0,0; write --position=-1,0)")
    p.add_argument("--noise", choices=NOISE_MODELS, default="none",
                   help="silhouette noise: none (default), or cheung: pixels missed and added and a few blobs, "
                        "as background subtraction leaves them (Cheung et al.)")
    p.add_argument("--surface", choices=SURFACES, default="skinned",
                   help="the body's surface: skinned (default: bends smoothly at the joints) or rigid (each "
                        "vertex moves with its own body part)")
    p.add_argument("--images", action="store_true", help="also render colour images and empty backgrounds")
    p.add_argument("--joint-map", type=Path, default=None, help="TOML joint-name overrides for the clip")
    p.add_argument("--seed", type=count(0), default=0,
                   help="seed of the noise, the colours and a posture's variations (default 0): the same seed, "
                        "the same sequence")
    add_overwrite_argument(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar, no summary")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def check_choice(flag: str, value, choices) -> None:
    if value is not None and value not in choices:
        raise UserError(f"{flag}: expected one of {', '.join(choices)}, got {value!r}")


def run(args) -> int:
    check_choice("--posture", args.posture, tuple(POSTURES))
    check_choice("--up", args.up, UP_AXES)
    check_choice("--prop", args.prop, PROPS)
    if args.posture is not None and (args.clip is not None or args.joint_map is not None):
        raise UserError("--posture: makes its own motion; give no --clip or --joint-map with it")
    clip = args.clip if args.clip is not None else DEFAULT_CLIP
    if args.posture is None and not clip.exists():
        raise InputFileError(clip, "missing")
    if not 1 <= args.cameras <= 64:
        raise UserError("--cameras must be between 1 and 64")
    if not 0.0 < args.radius <= MAX_STUDIO_M:  # NaN too
        raise UserError(f"--radius: expected 0 < metres <= {MAX_STUDIO_M:g}, got {args.radius}")
    if not 0.0 <= args.height <= MAX_STUDIO_M:
        raise UserError(f"--height: expected 0 <= metres <= {MAX_STUDIO_M:g}, got {args.height}")
    if not FOV_RANGE_DEG[0] <= args.fov <= FOV_RANGE_DEG[1]:
        raise UserError(f"--fov: expected {FOV_RANGE_DEG[0]:g}..{FOV_RANGE_DEG[1]:g} degrees, got {args.fov}")
    if not abs(args.distortion) <= MAX_DISTORTION_K1:
        raise UserError(f"--distortion: expected -{MAX_DISTORTION_K1:g} <= K1 <= {MAX_DISTORTION_K1:g}, "
                        f"got {args.distortion}")
    position = parse_position(args.position)
    sizes = parse_sizes(args.sizes) if args.sizes is not None else [parse_size(args.size or DEFAULT_SIZE)]
    if len(sizes) > args.cameras:
        raise UserError(f"--sizes: {len(sizes)} sizes for {args.cameras} cameras")
    studio = synth_studio(args.cameras, sizes, args.radius, args.height, args.fov, args.distortion)
    opts = SynthOptions(frames=args.frames, start=args.start, step=args.step, noise=args.noise,
                        surface=args.surface, seed=args.seed, images=args.images, up=args.up, prop=args.prop,
                        posture=args.posture, position=position)
    bar = Progress("synth", args.frames, enabled=None if not args.quiet else False)
    check_folder_target(args.out, ("*",), overwrite=args.overwrite, what="sequence")
    with staged_folder(args.out) as staged:  # a new folder whole, or the old one as it was
        summary = synthesize(load_body_model(), studio, clip, staged, opts, args.joint_map, bar)
    shown = {k: summary[k] for k in ("frames", "fps", "cameras", "noise", "surface")}
    if args.json:
        print(json.dumps({"out": str(args.out), **shown}))
    elif not args.quiet:
        noise = "no noise" if shown["noise"] == "none" else f"{shown['noise']} noise"
        print(f"wrote {args.out}: {shown['frames']} frames at {shown['fps']:g} fps from {shown['cameras']} cameras "
              f"({shown['surface']} surface, {noise}; truth.jsonl holds the true poses)")
        print(next_steps(f"mocap fit {shell_word(args.out)} --out RESULT"))
    return 0
