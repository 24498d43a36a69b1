"""`make demo`: the main job on built-in data, end to end.

A bundled real CMU walk drives the body in the virtual studio (8 cameras, 320x240, Cheung's
segmentation noise), the silhouettes are fitted, and the result folder gets the poses, BVH,
pictures, plots and a report page. Prints a small table at the end.

    mocap demo [--out demo] [--clip FILE.bvh] [--frames N] [--clients N]    (or python -m server.demo)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from common.body import load_body_model
from common.camera import circle_studio
from common.synth import SynthOptions, synthesize
from common.argtypes import OneLineParser, count
from common.errors import UserError
from server.commands.synth import DEFAULT_CLIP
from server.output import staged_folder

DEMO_FRAMES = 30
DEMO_MARK = ".mocap-demo"  # in a folder the demo made, which it may make again


def add_demo_arguments(ap) -> None:
    ap.add_argument("--out", type=Path, default=Path("demo"),
                    help="the demo's own folder, made again each run (one holding files the demo did not make "
                         "is refused)")
    ap.add_argument("--clip", type=Path, default=DEFAULT_CLIP, help="BVH motion (default: the bundled CMU walk)")
    ap.add_argument("--frames", type=count(1), default=DEMO_FRAMES,
                    help=f"frames of the clip to synthesise and fit (default {DEMO_FRAMES})")
    ap.add_argument("--clients", type=count(0), default=0, help="local limb clients (default 0: one process)")


def main(argv=None) -> int:
    ap = OneLineParser(prog="python -m server.demo", description=__doc__.splitlines()[0])
    add_demo_arguments(ap)
    try:
        return run_demo(ap.parse_args(argv))
    except UserError as exc:
        print(f"{ap.prog}: error: {exc}", file=sys.stderr)
        return 2


def claim_demo_folder(out: Path) -> None:
    """Make ``out`` the demo's folder, which every run makes again: refused where it holds files
    the demo did not make (no DEMO_MARK), so that ``--out`` naming a real take's folder loses
    nothing."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: is a file; name a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / DEMO_MARK).is_file():
        raise UserError(f"--out {out}: holds files the demo did not make, and the demo makes its folder again on "
                        "every run; choose another folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / DEMO_MARK).write_text("made by mocap demo: its sequence/ and result/ are made again on every run\n")


def run_demo(args) -> int:
    """The demo's three steps (``mocap demo``, ``make demo``)."""
    from server.cli import main as mocap

    claim_demo_folder(args.out)
    seq, result = args.out / "sequence", args.out / "result"
    print(f"1/3 virtual studio: {args.clip.name}, {args.frames} frames, 8 cameras, Cheung noise -> {seq}")
    with staged_folder(seq) as staged:  # the demo's own folder: made again on every run
        synthesize(load_body_model(), circle_studio(), args.clip, staged,
                   SynthOptions(frames=args.frames, noise="cheung", seed=0))
    print(f"2/3 fitting -> {result}")
    code = mocap(["fit", str(seq), "--out", str(result), "--quiet", "--overwrite", *(
        ["--clients", str(args.clients)] if args.clients else [])])
    if code:
        return code
    summary = json.loads((result / "summary.json").read_text())
    print("3/3 pictures and report")
    report = None
    try:
        from server.pictures import make_result_pictures
        from server.report import write_report
    except ImportError:
        make_result_pictures = write_report = None
    if make_result_pictures:
        make_result_pictures(result, seq)
        report = write_report(result, seq)
    print()
    print(f"  {'frames':22} {summary['frames']}")
    print(f"  {'seconds per frame':22} {summary['seconds_per_frame']:.3f} (tracking, median, {summary['mode']}) "
          f"+ {summary['refine_seconds_per_frame']:.3f} (refinement)")
    print(f"  {'mean joint error':22} {summary['mean_joint_error_mm']:.1f} mm "
          f"(tracking alone {summary['tracking_mean_joint_error_mm']:.1f} mm)")
    print(f"  {'max joint error':22} {summary['max_joint_error_mm']:.1f} mm "
          f"(tracking alone {summary['tracking_max_joint_error_mm']:.1f} mm)")
    print(f"  {'result':22} {result}/ (poses.jsonl, motion.bvh, summary.json)")
    if report:
        print(f"  {'report':22} {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
