"""``mocap live``: the real-time pipeline of Cheung et al. (2000, section 5) over a sequence.

One thread per stage, joined by bounded queues, so that the stages of successive frames
overlap as in the paper's timing diagram (numpy releases the GIL in the heavy parts):

    acquire -> [segment] -> voxels (SPOT) -> surface -> ellipsoids

``acquire`` reads the silhouettes, or the colour images when the sequence has no
silhouettes, in which case ``segment`` runs background subtraction (``common.segmentation``,
skipped when that module is not installed). The report gives, like the paper's Table 1,
the time per stage, the throughput in frames per second and the latency from acquisition
to fitted ellipsoids.
"""
from __future__ import annotations

import importlib
import json
import queue
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from common.ellipsoid_fit import SHELL_NAMES, fit_ellipsoids
from common.errors import InputFileError
from common.sequence import load_sequence, read_image
from common.argtypes import count, non_negative
from server.commands.fit import add_world_arguments
from server.output import add_units_argument
from common.voxels import SpotGrid, surface_voxels

QUEUE_DEPTH = 2  # frames waiting between two stages (bounded: a slow stage back-pressures)
STOP = None  # end-of-stream marker passed down the pipeline


@dataclass
class Item:
    """One frame travelling down the pipeline."""

    frame: int
    started: float  # perf_counter at the start of acquisition
    data: object = None
    result: object = None
    shells: object = None
    finished: float = 0.0


@dataclass
class StageTimes:
    name: str
    seconds: list = field(default_factory=list)


def register(subparsers) -> None:
    p = subparsers.add_parser("live", help="real-time pipeline: silhouettes -> voxels -> ellipsoids, timed",
                              description="Run the multi-threaded reconstruction pipeline over a sequence "
                                          "and report frames per second and latency per stage.")
    p.add_argument("sequence", type=Path, help="sequence folder (calibration.json + silhouettes/ or images/)")
    p.add_argument("--grid", type=count(2), default=64, help="voxels per side N of the N^3 grid (default 64)")
    p.add_argument("--q", type=count(1), default=2, help="SPOT sample pixels per voxel and camera (default 2)")
    p.add_argument("--frames", type=count(1), default=None, help="only the first N frames")
    p.add_argument("--repeat", type=count(1), default=1, help="run the frames this many times (steadier timing)")
    p.add_argument("--rate", type=non_negative, default=0.0,
                   help="feed frames at this many per second, like live cameras (default 0: as fast as possible)")
    p.add_argument("--method", default="cheung", help="background subtraction method when segmenting images")
    add_units_argument(p)
    add_world_arguments(p)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    seq = load_sequence(args.sequence, args.units, up=args.up, mask_threshold=args.mask_threshold,
                        clean_masks=args.clean_masks, calibration=args.calibration)
    frames = (seq.frames[:args.frames] if args.frames else seq.frames) * args.repeat
    acquire, segment = _sources(seq, args.method)
    grid = SpotGrid.build(seq.studio, grid=args.grid, q=args.q)
    stages = [("acquire", acquire)]
    if segment is not None:
        stages.append(("segment", segment))
    stages += [("voxels", lambda it: _voxels(grid, it)), ("surface", _surface), ("ellipsoids", _ellipsoids())]
    report = run_pipeline(frames, stages, args.rate)
    report.update({"sequence": str(seq.path), "grid": grid.grid, "q": grid.q, "cameras": len(seq.studio),
                   "rate": args.rate})
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        print_report(report)
    return 0


def _sources(seq, method: str):
    """(acquire, segment or None) stage functions for this sequence."""
    if seq.has_silhouettes:
        def acquire(item):
            item.data = seq.silhouettes(item.frame)
            return item
        return acquire, None
    if not (seq.path / "images").is_dir():
        raise InputFileError(seq.path, "no silhouettes/ and no images/ to reconstruct from")
    try:
        segmentation = importlib.import_module("common.segmentation")
    except ModuleNotFoundError as exc:
        if exc.name != "common.segmentation":
            raise
        raise InputFileError(seq.path / "silhouettes", "missing, and this build has no segmentation to make "
                                                       "them from images/") from None
    segmenters = []
    for cam in seq.studio:
        folder = seq.path / "background" / cam.name
        files = sorted(folder.glob("*.png")) if folder.is_dir() else []
        if not files:
            raise InputFileError(folder, f"missing: empty-studio frames of camera {cam.name} are needed to segment")
        backgrounds = np.stack([read_image(f, "RGB") for f in files])
        segmenters.append(segmentation.make_segmenter(method).fit(backgrounds))

    def acquire(item):
        item.data = seq.images(item.frame)
        return item

    def segment(item):
        item.data = np.stack([s.segment(img) for s, img in zip(segmenters, item.data)])
        return item

    return acquire, segment


def _voxels(grid: SpotGrid, item: Item) -> Item:
    item.result = grid.reconstruct(item.data, surface=False)
    return item


def _surface(item: Item) -> Item:
    r = item.result
    item.result = replace(r, surface=surface_voxels(r.occupied, r.box))
    item.data = item.result.surface_points()
    return item


def _ellipsoids():
    previous = [None]

    def fit(item: Item) -> Item:
        if len(item.data) >= 8:
            previous[0] = fit_ellipsoids(item.data, previous[0])
            item.shells = previous[0]
        return item

    return fit


def run_pipeline(frames, stages, rate: float = 0.0) -> dict:
    """Run ``stages`` [(name, fn(Item) -> Item)] in one thread each over ``frames``.

    rate: frames fed per second (0: as fast as the first stage takes them); at a rate the
    pipeline keeps up with, latency is the pipeline's own, without queueing.

    Returns {"frames", "seconds", "frames_per_second", "latency_ms" {mean, max},
    "stages": [{"name", "mean_ms", "max_ms"}], "shells_active" (last frame)}.
    """
    queues = [queue.Queue(maxsize=QUEUE_DEPTH) for _ in range(len(stages) + 1)]
    times = [StageTimes(name) for name, _ in stages]
    errors = []

    def worker(k: int, fn):
        while True:
            item = queues[k].get()
            if item is STOP:
                queues[k + 1].put(STOP)
                return
            if errors:
                continue  # drain until STOP, so no stage blocks on a full queue
            try:
                t0 = time.perf_counter()
                item = fn(item)
                times[k].seconds.append(time.perf_counter() - t0)
            except BaseException as exc:  # handed to the main thread, which re-raises it
                errors.append(exc)
                continue
            queues[k + 1].put(item)

    threads = [threading.Thread(target=worker, args=(k, fn), daemon=True) for k, (_, fn) in enumerate(stages)]
    for t in threads:
        t.start()
    done = []

    def sink():
        while True:
            item = queues[-1].get()
            if item is STOP:
                return
            item.finished = time.perf_counter()
            done.append(item)

    collector = threading.Thread(target=sink, daemon=True)
    collector.start()
    start = time.perf_counter()
    for i, frame in enumerate(frames):
        if errors:
            break
        if rate > 0:
            time.sleep(max(0.0, start + i / rate - time.perf_counter()))
        queues[0].put(Item(frame, time.perf_counter()))
    queues[0].put(STOP)
    for t in threads:
        t.join()
    collector.join()
    if errors:
        raise errors[0]
    elapsed = time.perf_counter() - start
    latency = np.array([it.finished - it.started for it in done]) * 1e3
    last = done[-1].shells if done else None
    return {
        "frames": len(done), "seconds": elapsed,
        "frames_per_second": len(done) / elapsed if elapsed > 0 else None,
        "latency_ms": {"mean": float(latency.mean()) if len(latency) else None,
                       "max": float(latency.max()) if len(latency) else None},
        "stages": [{"name": t.name, "mean_ms": 1e3 * float(np.mean(t.seconds)) if t.seconds else None,
                    "max_ms": 1e3 * float(np.max(t.seconds)) if t.seconds else None} for t in times],
        "shells_active": [n for n, a in zip(SHELL_NAMES, last.active) if a] if last is not None else [],
    }


def print_report(report: dict) -> None:
    print(f"  {report['frames']} frames, {report['cameras']} cameras, grid {report['grid']}^3, Q = {report['q']}")
    print(f"  {'step':<12}{'mean ms':>10}{'max ms':>10}")
    for s in report["stages"]:
        mean = f"{s['mean_ms']:.1f}" if s["mean_ms"] is not None else "-"
        peak = f"{s['max_ms']:.1f}" if s["max_ms"] is not None else "-"
        print(f"  {s['name']:<12}{mean:>10}{peak:>10}")
    fps = report["frames_per_second"]
    lat = report["latency_ms"]
    print(f"  throughput  {fps:.1f} frames/s" if fps else "  throughput  -")
    if lat["mean"] is not None:
        print(f"  latency     {lat['mean']:.1f} ms mean, {lat['max']:.1f} ms max (acquisition to ellipsoids)")
    print(f"  shells      {', '.join(report['shells_active']) or 'none'} (last frame)")
