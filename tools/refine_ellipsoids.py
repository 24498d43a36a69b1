"""Refine the per-segment ellipsoids so their silhouettes match the skinned surface's.

Run by maintainers after tools/build_body_model.py (the result is committed):
    python tools/refine_ellipsoids.py

The moment-based ellipsoids of build_body_model.py are a fair start, but the cpu energy's
accuracy depends on how closely the ellipsoids' silhouettes follow the real surface. Like the
paper's actor-specific shape adaptation, we fit each segment's ellipsoid (centre, radii, a
small rotation) to minimise the XOR between the ellipsoid body and the smoothly skinned mesh
rendered in the virtual studio, over poses taken from real motion. Segments are refined in
turn (coordinate descent), each by Powell's method over its 9 shape parameters.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common import optimize  # noqa: E402
from common.body import forward_kinematics, load_body_model, rotvec_to_matrix, skinned_vertices  # noqa: E402
from common.camera import circle_studio  # noqa: E402
from common.conic_bits import conic_coverage, xor_bits  # noqa: E402
from common.energy import image_conics, xor_span_sums  # noqa: E402
from common.motion_import import import_bvh  # noqa: E402
from common.render_gl import MeshRenderer  # noqa: E402

CLIPS = ("cmu_12_01_walk.bvh", "06_08.bvh", "05_10.bvh")
POSES_PER_CLIP = 6
ROUNDS = 2
SHAPE_STEPS = np.array([0.01] * 3 + [0.1] * 3 + [0.1] * 3)  # centre m, log-radii, rotation rad
SHAPE_LIMITS = np.array([[-0.05, 0.05]] * 3 + [[-0.5, 0.5]] * 3 + [[-0.6, 0.6]] * 3)


def main() -> None:
    model = load_body_model()
    studio = circle_studio(8, 320, 240)
    P = np.stack([c.projection_matrix for c in studio])
    K, H, W = len(studio), 240, 320
    y0 = np.zeros(K)
    x0 = np.zeros(K)
    poses = []
    for clip in CLIPS:
        path = ROOT / "common" / "data" / "clips" / clip
        from common.bvh import read_bvh

        n = read_bvh(path).num_frames
        idx = np.linspace(1, n - 1, POSES_PER_CLIP).astype(int)
        params = import_bvh(model, path, idx).params
        params[:, 0:2] = 0.0
        poses.append(params)
    params = np.concatenate(poses)
    fk = forward_kinematics(model, params)
    renderer = MeshRenderer(studio, model.triangles)
    targets = [np.stack(renderer.render_masks(skinned_vertices(model, fk, i))) for i in range(len(params))]

    centres = model.ellipsoid_centres.copy()
    axes = model.ellipsoid_axes.copy()
    radii = model.ellipsoid_radii.copy()

    def world(seg_c, seg_A, i, segs):
        R, o = fk.rotations[i, segs], fk.origins[i, segs]
        return np.einsum("sij,sj->si", R, seg_c) + o, R @ seg_A

    def shape_A(ax, rad):
        return ax * rad[..., None, :]

    def total_xor() -> int:
        tot = 0
        for i in range(len(params)):
            c, A = world(centres, shape_A(axes, radii), i, np.arange(16))
            C, ok = image_conics(P, c[None], A[None])
            tot += int((conic_coverage(C, ok, y0, x0, H, W)[0] ^ targets[i]).sum())
        return tot

    print("XOR before:", total_xor())
    for rnd in range(ROUNDS):
        for seg in range(16):
            others = [s for s in range(16) if s != seg]
            values, bases = [], []
            for i in range(len(params)):
                c, A = world(centres[others], shape_A(axes[others], radii[others]), i, others)
                C, ok = image_conics(P, c[None], A[None])
                gain, loss, base = xor_bits(conic_coverage(C, ok, y0, x0, H, W)[0], np.ascontiguousarray(targets[i], bool))
                values.append((gain, loss))
                bases.append(int(base.sum()))

            def f(Z):
                c_loc = centres[seg] + Z[:, 0:3]
                rad = radii[seg] * np.exp(Z[:, 3:6])
                ax = rotvec_to_matrix(Z[:, 6:9]) @ axes[seg]
                A_loc = ax * rad[:, None, :]
                out = np.zeros(len(Z))
                for i in range(len(params)):
                    R, o = fk.rotations[i, seg], fk.origins[i, seg]
                    cw = (c_loc @ R.T + o)[:, None]
                    Aw = (R @ A_loc)[:, None]
                    C, ok = image_conics(P, cw, Aw)
                    out += bases[i] + xor_span_sums(C, ok, y0, x0, H, W, *values[i], np.ones(len(P)))
                return out

            res = optimize.powell(f, np.zeros(9), SHAPE_LIMITS[:, 0], SHAPE_LIMITS[:, 1], SHAPE_STEPS,
                                  xtol=0.05, max_evals=600)
            z = res.x
            centres[seg] = centres[seg] + z[0:3]
            radii[seg] = radii[seg] * np.exp(z[3:6])
            axes[seg] = rotvec_to_matrix(z[6:9]) @ axes[seg]
            print(f"round {rnd} segment {seg}: XOR {res.fun:.0f} ({res.nfev} evaluations)", flush=True)
        print("XOR after round", rnd, ":", total_xor())

    path = ROOT / "common" / "data" / "body_model.npz"
    data = dict(np.load(path))
    data.update(ellipsoid_centres=centres, ellipsoid_axes=axes, ellipsoid_radii=radii)
    np.savez_compressed(path, **data)
    print("wrote", path)


if __name__ == "__main__":
    main()
