"""mocap bench: measure the numbers of DESIGN.md section 9 and write them as JSON."""
from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

from common.errors import UserError
from common.argtypes import count, non_negative, real

BENCH_CLIP_FRAMES = 20  # frames of the bundled walk used for fitting benchmarks


JSON_HELP = "also write the figures to this JSON file"
FRAMES_HELP = "frames of the sequence to fit"


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks")  # the list of them is added below, once they are registered
    bsub = p.add_subparsers(dest="bench", metavar="WHAT")
    bsub.required = True
    e = bsub.add_parser("energy", help="XOR energy evaluations per second (paper Table 1)")
    e.add_argument("--backends", default="cpu,gl", help="energy backends, comma separated (gl needs OpenGL)")
    e.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    f = bsub.add_parser("fit", help="seconds per frame, single process (paper Table 2)")
    f.add_argument("sequence", type=Path, nargs="?", default=None,
                   help="sequence folder (default: synthesise the bundled walk)")
    f.add_argument("--frames", type=count(1), default=BENCH_CLIP_FRAMES, help=FRAMES_HELP)
    f.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    c = bsub.add_parser("cluster", help="single process vs server + clients (paper Table 2)")
    c.add_argument("sequence", type=Path, help="sequence folder")
    c.add_argument("--frames", type=count(1), default=BENCH_CLIP_FRAMES, help=FRAMES_HELP)
    c.add_argument("--clients", type=count(0), default=4, help="local clients beside the server")
    c.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    h = bsub.add_parser("hops", help="the refinement's hops, single process vs server + clients side by side")
    h.add_argument("sequence", type=Path, help="sequence folder")
    h.add_argument("--frames", type=count(1), default=10, help=FRAMES_HELP)
    h.add_argument("--clients", type=count(0), default=4, help="local clients beside the server")
    h.add_argument("--hops", type=count(0), default=20, metavar="N", help="as mocap fit --refine-hops")
    h.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    s = bsub.add_parser("segment", help="background subtraction frames/s and error rates")
    s.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    v = bsub.add_parser("voxels", help="SPOT voxel reconstruction frames/s")
    v.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    cl = bsub.add_parser("clean", help="multi-view cleaning of a frame's masks frames/s")
    cl.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    acc = bsub.add_parser("accuracy", help="joint error on walk, dance and basketball clips (virtual studio)")
    acc.add_argument("--frames", type=count(1), default=100, help="frames of each clip")
    acc.add_argument("--turn-hypotheses", type=count(0), default=None, metavar="N",
                     help="as mocap fit --turn-hypotheses (default: its default)")
    acc.add_argument("--turn-step", type=real(0.0, math.pi, exclusive_minimum=True), default=None, metavar="RAD",
                     help="as Config.toml's [fit] turn_step (default: its default)")
    acc.add_argument("--no-redetect", action="store_true", help="as Config.toml's [fit] redetect = false")
    acc.add_argument("--spine-twist-prior", type=non_negative, default=None, metavar="PX_PER_RAD2",
                     help="as Config.toml's [fit] spine_twist_prior (default: its default)")
    acc.add_argument("--refine-passes", type=count(0), default=None, metavar="N",
                     help="as mocap fit --refine-passes (default: its default)")
    acc.add_argument("--refine-search", action="store_true", help="as mocap fit --refine-search")
    acc.add_argument("--refine-hops", type=count(0), default=None, metavar="N", help="as mocap fit --refine-hops")
    acc.add_argument("--energy", default="cpu",
                     help="energy backends to compare on the same sequences, comma separated (e.g. cpu,volume)")
    acc.add_argument("--no-restart", action="store_true",
                     help="skip tracking the last 40 frames again from the truth of the first of them (drift_mm)")
    acc.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    ini = bsub.add_parser("init", help="automatic first-frame initialisation on every clip")
    ini.add_argument("clips", type=Path, nargs="*",
                     help="BVH clips (default: all of ../shared/data/mocap if there, else the bundled ones)")
    ini.add_argument("--bundled", action="store_true", help="the bundled clips, even where shared data exists")
    ini.add_argument("--tpose", action="store_true", help="also start at frame 0 (the CMU clips' added T-pose)")
    ini.add_argument("--frames", type=count(1), default=10, help="frames fitted from each start")
    ini.add_argument("--first-frame-only", action="store_true",
                     help="fit only the first frame of each run (the search alone), on the same clips and starts")
    ini.add_argument("--refine-search", action="store_true", help="both runs as mocap fit --refine-search")
    ini.add_argument("--refine-hops", type=count(0), default=0, metavar="N", help="both runs as mocap fit --refine-hops")
    ini.add_argument("--jobs", type=count(1), default=1,
                     help="starts fitted at once, one process (and core) each; the same rows as one")
    ini.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    pr = bsub.add_parser("presets", help="mocap fit --preset fast|default|best on the same frames: time and error")
    pr.add_argument("sequence", type=Path, nargs="?", default=None,
                    help="sequence folder (default: synthesise the bundled walk)")
    pr.add_argument("--frames", type=count(1), default=BENCH_CLIP_FRAMES, help=FRAMES_HELP)
    pr.add_argument("--presets", default=None, help="comma-separated (default: all)")
    pr.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    bb = bsub.add_parser("batch", help="mocap batch against a serial loop of mocap run, on the same takes")
    bb.add_argument("--takes", type=count(1), default=4, help="synthetic takes in the project")
    bb.add_argument("--frames", type=count(1), default=20, help="frames per take")
    bb.add_argument("--workers", type=count(1), default=2, help="batch workers (processes)")
    bb.add_argument("--json", type=Path, default=None, metavar="FILE", help=JSON_HELP)
    a = bsub.add_parser("all", help="everything, into a folder of JSON files")
    a.add_argument("--out", type=Path, default=Path("bench"), help="folder for the JSON files")
    a.add_argument("--frames", type=count(1), default=BENCH_CLIP_FRAMES, help=FRAMES_HELP)
    p.set_defaults(func=run)
    # mocap --help's line: argparse keeps a subcommand's help in a pseudo-action it does not return
    listed = next(a for a in sub._choices_actions if a.dest == "bench")
    listed.help = f"benchmarks ({', '.join(bsub.choices)})"


def _fit_options(**fields):
    """FitOptions(**fields); a value out of range is the user's error, naming the option.
    (Imported here: the CLI's start stays cheap for the benches that do not fit.)"""
    from common.fitting import FitOptions

    try:
        return FitOptions(**fields)
    except ValueError as exc:
        raise UserError(f"bad option: {exc}") from None


def _emit(rows, path: Path | None) -> None:
    from server.benchmarks import write_json

    if path:
        write_json(path, rows)
    print(json.dumps(rows, indent=1))


def bench_sequence(frames: int, workdir: Path) -> Path:
    """The bundled walk in the virtual studio with Cheung noise: the standard fitting benchmark."""
    from common.body import load_body_model
    from common.camera import circle_studio
    from common.synth import SynthOptions, synthesize
    from server.commands.synth import DEFAULT_CLIP

    seq = workdir / "bench-walk"
    if not (seq / "sequence.json").exists():
        synthesize(load_body_model(), circle_studio(), DEFAULT_CLIP, seq,
                   SynthOptions(frames=frames, noise="cheung", seed=0))
    return seq


def run(args) -> int:
    from server import benchmarks

    if args.bench == "energy":
        rows = benchmarks.energy_rows(tuple(b for b in args.backends.split(",") if b))
        benchmarks.print_energy_table(rows)
        if args.json:
            benchmarks.write_json(args.json, rows)
        return 0
    if args.bench == "fit":
        with tempfile.TemporaryDirectory() as tmp:
            seq = args.sequence or bench_sequence(args.frames, Path(tmp))
            _emit(benchmarks.fit_rows(seq, args.frames), args.json)
        return 0
    if args.bench == "cluster":
        from server.bench_cluster import bench_cluster

        if not args.sequence.exists():
            raise UserError(f"{args.sequence}: no such sequence")
        _emit(bench_cluster(args.sequence, args.frames, args.clients), args.json)
        return 0
    if args.bench == "hops":
        from server.bench_cluster import bench_hops

        if not args.sequence.exists():
            raise UserError(f"{args.sequence}: no such sequence")
        if args.hops < 1 or args.clients < 1 or args.frames < 2:
            raise UserError("bench hops needs --hops >= 1, --clients >= 1 and --frames >= 2")
        _emit(bench_hops(args.sequence, args.frames, args.clients, args.hops), args.json)
        return 0
    if args.bench == "accuracy":
        with tempfile.TemporaryDirectory() as tmp:
            rows = []
            chosen = {name: value for name, value in (("turn_hypotheses", args.turn_hypotheses),
                                                     ("turn_step_rad", args.turn_step),
                                                     ("refine_passes", args.refine_passes),
                                                     ("refine_search", args.refine_search or None),
                                                     ("refine_hops", args.refine_hops),
                                                     ("spine_twist_prior", args.spine_twist_prior)) if value is not None}
            for backend in [b for b in args.energy.split(",") if b]:
                options = _fit_options(energy=backend,
                                       redetect_limbs=not args.no_redetect, **chosen)
                rows += benchmarks.accuracy_rows(args.frames, Path(tmp), options=options, restart=not args.no_restart)
            _emit(rows, args.json)
        return 0
    if args.bench == "init":
        clip_dir = Path(__file__).resolve().parents[2] / "common" / "data" / "clips"
        clips = args.clips or (not args.bundled and benchmarks.shared_clips()) or sorted(clip_dir.glob("*.bvh"))
        missing = [c for c in clips if not c.exists()]
        if missing:
            raise UserError(f"{missing[0]}: no such clip")
        with tempfile.TemporaryDirectory() as tmp:
            options = _fit_options(refine_search=args.refine_search, refine_hops=args.refine_hops)
            rows = benchmarks.init_rows(clips, args.frames, Path(tmp), tpose=args.tpose, options=options,
                                        first_frame_only=args.first_frame_only, jobs=args.jobs)
        if args.json:
            benchmarks.write_json(args.json, rows)
        benchmarks.print_init_table(rows)
        return 0
    if args.bench == "presets":
        with tempfile.TemporaryDirectory() as tmp:
            seq = args.sequence or bench_sequence(args.frames, Path(tmp))
            chosen = [v for v in args.presets.split(",") if v] if args.presets else None
            _emit(benchmarks.preset_rows(seq, args.frames, Path(tmp), chosen), args.json)
        return 0
    if args.bench == "batch":
        from server.bench_batch import bench_batch

        _emit(bench_batch(args.takes, args.frames, args.workers), args.json)
        return 0
    if args.bench == "segment":
        from common.segmentation import bench_segmentation

        _emit(bench_segmentation(), args.json)
        return 0
    if args.bench == "voxels":
        from common.voxels import bench_voxels

        _emit(bench_voxels(), args.json)
        return 0
    if args.bench == "clean":
        from common.consistency import bench_cleaning

        _emit(bench_cleaning(), args.json)
        return 0
    return run_all(args.out, args.frames)


def run_all(out: Path, frames: int) -> int:
    from server import benchmarks

    out.mkdir(parents=True, exist_ok=True)
    rows = benchmarks.energy_rows()
    benchmarks.print_energy_table(rows)
    benchmarks.write_json(out / "energy.json", rows)
    with tempfile.TemporaryDirectory() as tmp:
        seq = bench_sequence(frames, Path(tmp))
        fit = benchmarks.fit_rows(seq, frames)
        try:
            from server.bench_cluster import bench_cluster

            cluster = bench_cluster(seq, frames, 4)
            benchmarks.write_json(out / "cluster.json", cluster)
            fit.append({"mode": "distributed", "energy_backend": "cpu", "clients": cluster.get("clients"),
                        "seconds_per_frame": cluster.get("distributed_seconds_per_frame"),
                        "paper_seconds_per_frame": benchmarks.PAPER_TABLE2["distributed"]})
        except ImportError:
            pass
        benchmarks.write_json(out / "fit.json", fit)
        print(json.dumps(fit, indent=1))
        presets = benchmarks.preset_rows(seq, frames, Path(tmp))
        benchmarks.write_json(out / "presets.json", presets)
        print(json.dumps(presets, indent=1))
    for name, module, func in (("segment", "common.segmentation", "bench_segmentation"),
                               ("voxels", "common.voxels", "bench_voxels"),
                               ("clean", "common.consistency", "bench_cleaning"),
                               ("batch", "server.bench_batch", "bench_batch")):
        try:
            mod = __import__(module, fromlist=[func])
        except ImportError:
            continue
        rows = getattr(mod, func)()
        benchmarks.write_json(out / f"{name}.json", rows)
        print(json.dumps(rows, indent=1))
    return 0
