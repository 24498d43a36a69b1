"""How well `mocap sync` finds cameras out of step, on a sequence that is in step.

    python tools/sync_trials.py SEQUENCE [--offsets -3,-1,2,4] [--pairs]
    python tools/sync_trials.py SEQUENCE --late-copy CAM=N --out DIR

Trials: each camera in turn is put N frames out of step (its frame j shows the others' frame
j - N, as if it had started recording N frames before them: its offset is N; for each N of
--offsets; with --pairs also every pair of cameras, the second at the next offset
of the list) and ``common.sync.estimate_offsets`` is run. Each camera out of step gets a verdict
(``VERDICTS``: its offset found sharp, found but not sharp, not told, or wrong), and a camera in
step that was given an offset is counted. Prints one line per trial and the counts.

--late-copy writes a copy of SEQUENCE with camera CAM's silhouettes renumbered so (file j holds
frame j - N), to fit and compare with the sequence in step.
"""
from __future__ import annotations

import argparse
import itertools
import shutil
import sys
import time
from functools import lru_cache
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common.sequence import load_sequence  # noqa: E402
from common.sync import estimate_offsets  # noqa: E402


def late_mask_of(seq, late: dict):
    """mask_of(k, i) (``common.sync.estimate_offsets``) of ``seq`` with camera index k out of
    step by ``late[k]``: its frame i shows the others' frame i - late[k] (its offset is
    late[k]; the first or last frame where that is outside the take)."""
    @lru_cache(maxsize=None)
    def frame(i):
        return seq.raw_silhouettes(seq.frames[min(max(i, 0), len(seq.frames) - 1)])

    def mask_of(k, i):
        cam = seq.studio[k]
        return frame(i - late.get(k, 0))[k, :cam.height, :cam.width]
    return mask_of


VERDICTS = ("sharp and right", "right, not sharp", "not told", "wrong, not sharp", "wrong and sharp")
IN_STEP = ("in step given an offset", "in step given an offset, not sharp")


def judge(estimate, late: dict) -> list[str]:
    """A verdict (``VERDICTS``) for each camera put out of step, and for each camera in step
    that was given an offset "in step given an offset" (sharp) or "... not sharp"."""
    verdicts = []
    for k, c in enumerate(estimate.cameras):
        truth = late.get(k, 0)
        if k not in late:
            if c.offset:
                verdicts.append(IN_STEP[0] if c.resolved else IN_STEP[1])
        elif c.offset == truth:
            verdicts.append(VERDICTS[0] if c.resolved else VERDICTS[1])
        elif c.offset == 0 and not c.resolved:
            verdicts.append(VERDICTS[2])
        else:
            verdicts.append(VERDICTS[4] if c.resolved else VERDICTS[3])
    return verdicts


def late_copy(src: Path, out: Path, camera: str, late: int) -> None:
    """A copy of the sequence ``src`` at ``out`` whose ``camera`` is out of step by ``late``
    frames (file j holds frame j - late: its offset is late), the first (or last) frame
    repeated where none is left."""
    shutil.copytree(src, out)
    folder = out / "silhouettes" / camera
    names = sorted(folder.iterdir())
    data = [p.read_bytes() for p in names]
    for j, path in enumerate(names):
        path.write_bytes(data[min(max(j - late, 0), len(data) - 1)])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--offsets", default="-3,-1,2,4", help="offsets tried, comma-separated")
    ap.add_argument("--pairs", action="store_true", help="also every pair of cameras out of step")
    ap.add_argument("--late-copy", metavar="CAM=N", help="write a copy with camera CAM out of step by N")
    ap.add_argument("--out", type=Path, help="where --late-copy writes")
    args = ap.parse_args(argv)
    if args.late_copy:
        camera, late = args.late_copy.split("=")
        late_copy(args.sequence, args.out, camera, int(late))
        return
    seq = load_sequence(args.sequence, clean_masks=False)
    names = [c.name for c in seq.studio]
    offsets = [int(v) for v in args.offsets.split(",")]
    trials = [{k: n} for k in range(len(names)) for n in offsets]
    if args.pairs:
        trials += [{a: n, b: offsets[(i + 1) % len(offsets)]}
                   for a, b in itertools.combinations(range(len(names)), 2) for i, n in enumerate(offsets)]
    counts = {v: 0 for v in (*VERDICTS, *IN_STEP)}
    t0 = time.perf_counter()
    for late in trials:
        estimate = estimate_offsets(seq.studio, late_mask_of(seq, late), len(seq.frames))
        verdicts = judge(estimate, late)
        for v in verdicts:
            counts[v] += 1
        given = " ".join(f"{c.camera}={c.offset}{'' if c.resolved else '?'}" for c in estimate.cameras)
        print(f"{', '.join(f'{names[k]} {n:+d}' for k, n in late.items()):<20} {'; '.join(verdicts):<36} {given}",
              flush=True)
    print(f"{len(trials)} trials, cameras out of step: " + ", ".join(f"{counts[v]} {v}" for v in VERDICTS)
          + f"; cameras in step given an offset: {counts[IN_STEP[0]]} sharp, {counts[IN_STEP[1]]} not sharp; "
          f"{(time.perf_counter() - t0) / len(trials):.1f} s a trial")

if __name__ == "__main__":
    main()
