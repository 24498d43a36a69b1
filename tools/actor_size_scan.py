"""How a sequence's first frame fits at each actor size: what `mocap fit`'s size search sees.

    python tools/actor_size_scan.py SEQUENCE [--scales 0.9,1.0,...,1.6] [--girths 1.0,1.2,...]
                                    [--ruler OUT.png] [--fit-take SCALE,GIRTH --out RESULT]

The first frame is searched at the model's size (the WIDE schedule from the voxel starts, as
``server.session.choose_actor_scale`` does), then that pose is fitted again at each size
(``server.session.fit_at_scale``). Per size it prints the XOR energy, its two parts (model
pixels outside the silhouettes and silhouette pixels the model misses) and the size search's
score (``common.scoring.size_score``). Where the XOR keeps falling while the model stays inside
the silhouettes, the masks hold foreground that no body explains (a prop, a mask, loose clothes).

``--girths``: each size also fitted with the body thicker or thinner than the model's (every
ellipsoid's radii across its longest axis times the factor, the bones as they are), a shape
fitted as Theobalt et al.'s initialisation conforms the model to its actor; `mocap fit` keeps
the model's shape (docs/accuracy.md, "The body's girth chosen by the first frame: measured, not
kept"). ``--fit-take SCALE,GIRTH --out RESULT``: instead, the whole take fitted as `mocap fit`
fits it (default settings, both cores, its first frame searched) with the body at that size and
girth, and its figures printed as tools/posture_report.py prints them.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common.body import BodyModel, load_body_model  # noqa: E402
from common.fitting import FitOptions, full_energy  # noqa: E402
from common.proposals import voxel_starts  # noqa: E402
from common.scoring import silhouette_disagreement, size_score  # noqa: E402
from common.search import WIDE, run_schedule  # noqa: E402
from common.sequence import load_sequence  # noqa: E402
from common.voxels import silhouette_centre  # noqa: E402
from server.session import ACTOR_SCALES, LocalSolver, context, fit_at_scale, frame_data, run_fit  # noqa: E402
from server.threads import usable_cores  # noqa: E402

RULER_STEP = 0.25     # the sequence's world units (metres) per ruler segment
RULER_LENGTH = 2.5    # ... the ruler's length


def draw_ruler(seq, frame: int, out: Path) -> None:
    """The first frame's colour images side by side with the ruler drawn in (see the docstring)."""
    from PIL import Image, ImageDraw

    centre = silhouette_centre(seq.studio, seq.silhouettes(frame))
    heights = np.arange(0.0, RULER_LENGTH + 1e-9, RULER_STEP)
    pictures = []
    for cam in seq.studio:
        picture = Image.fromarray(seq.image(cam, frame))
        draw = ImageDraw.Draw(picture)
        uv = cam.project(np.array([[centre[0], centre[1], h] for h in heights]))
        for k in range(len(heights) - 1):
            draw.line([tuple(uv[k]), tuple(uv[k + 1])], fill=(255, 0, 0) if k % 2 == 0 else (255, 255, 0), width=3)
        pictures.append(np.asarray(picture))
    height = max(p.shape[0] for p in pictures)
    row = [np.pad(p, ((0, height - p.shape[0]), (0, 0), (0, 0))) for p in pictures]
    Image.fromarray(np.concatenate(row, axis=1)).save(out)
    print(f"wrote {out}: a ruler of {RULER_LENGTH} units in {RULER_STEP}-unit segments (red from the floor)")


def thickened(model: BodyModel, girth: float) -> BodyModel:
    """``model`` with every ellipsoid's two shorter radii times ``girth`` (the longest, along the
    bone for a limb, kept): a stouter or slimmer actor of the same bones."""
    radii = np.array(model.ellipsoid_radii)
    rows, longest = np.arange(len(radii)), radii.argmax(axis=1)
    thick = radii * girth
    thick[rows, longest] = radii[rows, longest]
    return BodyModel(model.joint_rest, model.vertices, model.triangles, model.triangle_segment, model.vertex_segment,
                     model.skin_weights, model.ellipsoid_centres, model.ellipsoid_axes, thick, model.scale)


def fit_take(seq, scale: float, girth: float, out: Path) -> None:
    from posture_report import main as posture_report

    model, options = thickened(load_body_model().scaled(scale), girth), FitOptions()
    solver = LocalSolver(model, options, threads=usable_cores())
    try:
        run_fit(model, seq, out, options, solver, init="auto", overwrite=True)
    finally:
        solver.close()
    posture_report([str(out)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--scales", default=",".join(map(str, ACTOR_SCALES)), help="sizes over the model's, comma-separated")
    ap.add_argument("--girths", default="1.0", help="girths over the model's, comma-separated (see the docstring)")
    ap.add_argument("--ruler", type=Path, default=None, metavar="OUT.png", help="also draw the ruler picture")
    ap.add_argument("--fit-take", default=None, metavar="SCALE,GIRTH", help="fit the whole take with this body")
    ap.add_argument("--out", type=Path, default=None, help="--fit-take's result folder (replaced)")
    args = ap.parse_args()
    seq = load_sequence(args.sequence)
    model, options = load_body_model(), FitOptions()
    if args.fit_take:
        fit_take(seq, *(float(v) for v in args.fit_take.split(",")), args.out)
        return
    frame = seq.frames[0]
    if args.ruler:
        draw_ruler(seq, frame, args.ruler)
    data = frame_data(model, seq, frame)
    ctx = context(model, data, frame, options, LocalSolver(model, options), starts=tuple(voxel_starts(model, data)))
    found = run_schedule(ctx, WIDE)
    print(f"frame {frame}: silhouette {int(np.count_nonzero(data.masks))} px")
    girths = [float(g) for g in args.girths.split(",")]
    for scale in (float(s) for s in args.scales.split(",")):
        for girth in girths:
            actor, actor_data, fit = fit_at_scale(thickened(model, girth), seq, frame, found.params, scale, options)
            outside, missed = (int(v) for v in silhouette_disagreement(actor_data, fit.params).sum(axis=0))
            shape = f" girth {girth:.2f}" if girths != [1.0] else ""
            print(f"scale {scale:.2f}{shape}: XOR {full_energy(actor, actor_data, fit.params)}  {outside} model pixels "
                  f"outside the silhouettes, {missed} missed; size score {size_score(actor_data, fit, scale > 1.0):.0f}")


if __name__ == "__main__":
    main()
