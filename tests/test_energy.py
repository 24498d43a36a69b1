"""The cpu XOR energy: equals an explicit popcount, batches, pre-rendering, and the analytic
ellipsoid silhouettes agree with a tessellated ellipsoid mesh rendered by OpenGL."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from common.body import CHAINS, PARAM_COUNT, clip_to_limits, forward_kinematics, rest_params
from common.camera import circle_studio
from common.energy import (ARM_WINDOW, SMALL_WINDOW, CpuEnergy, EnergySetup, Window, counted_bounds, ellipsoid_world,
                           window_origins)
from common.objective import make_energy
from common.fitting import FrameData

# Measured (64x32 sphere): 0.1% of the silhouette; 48x24 (used here, faster) about 0.2%.
MESH_MISMATCH = 0.01  # XOR pixels / union pixels
RESAMPLED_MISMATCH = 0.025  # the same after undistorting the silhouettes (nearest pixel)
SPHERE_SEGMENTS = (48, 24)  # longitude, latitude divisions


def perturbed(base: np.ndarray, rng, n: int, spread: float = 0.15, indices=None) -> np.ndarray:
    """(n, 35) poses near ``base``: uniform noise on ``indices`` (default: every angle, 3 cm on the root)."""
    p = np.repeat(np.asarray(base, dtype=np.float64)[None], n, axis=0)
    idx = np.arange(3, PARAM_COUNT) if indices is None else np.asarray(indices)
    p[:, idx] += rng.uniform(-spread, spread, (n, len(idx)))
    if indices is None:
        p[:, 0:3] += rng.uniform(-0.03, 0.03, (n, 3))
    return clip_to_limits(p)


@pytest.fixture(scope="module")
def frame(model, small_loaded):
    seq, truth = small_loaded
    f = seq.frames[0]
    return FrameData(model, seq.studio, seq.silhouettes(f)), truth[f].params


def weighted(setup: EnergySetup, per_camera) -> float:
    """What an energy of ``setup`` counts for ``per_camera`` (K,) pixels: their sum, each
    camera's times its weight (``camera_weights``; exact: the weights are dyadic)."""
    weights = np.ones(len(setup.studio)) if setup.weights is None else setup.weights
    return float(np.asarray(per_camera) @ weights)


def setups(frame_data: FrameData, x: np.ndarray):
    """(name, EnergySetup) for every kind of window the fitter uses."""
    arm = CHAINS["left_arm"].segments
    leg = CHAINS["right_leg"].segments
    return [
        ("full", frame_data.full_setup(x)),
        ("half", frame_data.full_setup(x, half=True)),
        ("arm128_prerender", replace(frame_data.window_setup(x, arm[:2], ARM_WINDOW, True), moving=arm)),
        ("leg128", replace(frame_data.window_setup(x, leg[:2], ARM_WINDOW, False), moving=leg)),
        ("head64_prerender", frame_data.window_setup(x, CHAINS["head"].segments, SMALL_WINDOW, True)),
    ]


def test_energy_is_the_popcount_of_render_xor_input(model, frame, rng):
    data, truth = frame
    for name, setup in setups(data, truth):
        energy = CpuEnergy(model, setup)
        poses = perturbed(truth, rng, 6)
        for p in poses:
            rendered = energy.render(p)
            assert rendered.shape == setup.input_windows.shape
            assert rendered.any(), name
            expected = weighted(setup, np.count_nonzero(rendered ^ setup.input_windows, axis=(1, 2)))
            assert energy(p)[0] == expected, name


def test_compiled_span_sums_equal_per_pixel_sums_of_the_rendered_union(model, frame, rng):
    """The compiled conic rasteriser against the conics evaluated at every pixel centre, and
    the span sums against summing the per-pixel values over that coverage: overlapping
    segments counted once, spans clipped at window edges, several poses in one batch."""
    from common.conic_bits import conic_coverage
    from common.energy import image_conics, xor_span_sums

    data, x = frame
    energy = CpuEnergy(model, data.full_setup(x))
    poses = perturbed(x, rng, 4, spread=0.3)
    poses[:, 0] += 0.8  # half the body past the image edge in some cameras
    pose = forward_kinematics(model, poses)
    centres, A = ellipsoid_world(model, pose.rotations, pose.origins, range(16))
    C, drawable = image_conics(energy.P, centres, A)
    K, rows, width = len(energy.P), energy.rows, energy.width
    covered = conic_coverage(C, drawable, energy.y0, energy.x0, rows, width)
    ys, xs = np.mgrid[0:rows, 0:width].astype(np.float64)
    for b in range(len(poses)):
        for k in range(K):
            h = np.stack([xs + energy.x0[k], ys + energy.y0[k], np.ones_like(xs)], axis=-1)  # pixel centres
            inside = np.einsum("...i,sij,...j->s...", h, C[b, k], h) < 0
            brute = (inside & drawable[b, k][:, None, None]).any(axis=0)
            # a pixel centre within rounding of a conic's edge may fall either way
            assert np.count_nonzero(brute != covered[b, k]) <= 2, (b, k)
    assert covered.any()
    # the value covering a pixel adds: 0 where static (or outside the window), else 1 - 2 * input
    static = energy.static_mask if energy.counted is None else energy.static_mask | ~energy.counted
    values = np.where(static, 0, 1 - 2 * data.full_setup(x).inputs.astype(np.int64))
    unpack = lambda words: np.unpackbits(words.view(np.uint8), axis=-1, bitorder="little")[..., :width].astype(bool)
    np.testing.assert_array_equal(unpack(energy.gain), values == 1)
    np.testing.assert_array_equal(unpack(energy.loss), values == -1)
    sums = xor_span_sums(C, drawable, energy.y0, energy.x0, rows, width, energy.gain, energy.loss, energy.weights)
    np.testing.assert_array_equal(sums, [np.where(c, values, 0).sum(axis=(1, 2)) @ energy.weights for c in covered])
    assert (energy(poses) == energy.base + sums).all()


def test_image_conics_are_the_adjugate_of_the_projected_dual_quadric(rng):
    """The compiled conics (D = M M^T - x x^T with P T = [M, x]) against the textbook ones: the
    adjugate of P Q* P^T, Q* = T diag(1, 1, 1, -1) T^T, signed negative at the projected
    centre; and the points on each ellipsoid's rim (tangent to the viewing ray) on its conic."""
    from common.energy import image_conics

    K, B, S = 3, 2, 4
    studio = circle_studio(K, radius=3.0)
    P = studio.projection_matrices
    centres = rng.uniform(-0.4, 0.4, (B, S, 3)) + [0.0, 0.0, 1.0]
    A = np.einsum("bsij,bsj->bsij", np.linalg.qr(rng.standard_normal((B, S, 3, 3)))[0],
                  rng.uniform(0.03, 0.2, (B, S, 3)))  # rotation times radii
    C, drawable = image_conics(P, centres, A)
    assert drawable.all()
    for b in range(B):
        for k in range(K):
            for s in range(S):
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = A[b, s], centres[b, s]
                D = P[k] @ T @ np.diag([1.0, 1.0, 1.0, -1.0]) @ T.T @ P[k].T
                adj = np.linalg.inv(D) * np.linalg.det(D)
                x = P[k] @ np.append(centres[b, s], 1.0)
                expected = adj if x @ adj @ x < 0 else -adj
                np.testing.assert_allclose(C[b, k, s], expected, rtol=1e-9, atol=1e-9 * np.abs(adj).max())
                # rim points: u on the unit sphere with the ray from the camera centre tangent
                # to the ellipsoid there (grad . (p - o) = 0): the small circle u . d = 1
                o = studio.cameras[k].center
                d = np.linalg.solve(A[b, s], o - centres[b, s])  # the camera centre in sphere units
                e1 = np.cross(d, [0.3, 0.5, 0.8])
                e1 /= np.linalg.norm(e1)
                e2 = np.cross(d, e1) / np.linalg.norm(d)
                for angle in np.linspace(0.0, 2 * np.pi, 6, endpoint=False):
                    u = np.cos(angle) * e1 + np.sin(angle) * e2  # the great circle u . d = 0 ...
                    u = u * np.sqrt(1 - 1 / d.dot(d)) + d / d.dot(d)  # ... shrunk and moved to u . d = 1
                    h = P[k] @ np.append(centres[b, s] + A[b, s] @ u, 1.0)
                    h /= np.linalg.norm(h)
                    assert abs(h @ C[b, k, s] @ h) < 1e-9 * np.abs(C[b, k, s]).max()


def test_energy_is_not_trivially_zero(model, frame):
    """At the truth the model covers most of the input; far off it does not."""
    data, truth = frame
    energy = CpuEnergy(model, data.full_setup(truth))
    e_truth = int(energy(truth)[0])
    away = truth.copy()
    away[0] += 0.3
    assert 0 < e_truth < 0.5 * data.masks.sum()
    assert int(energy(away)[0]) > 2 * e_truth


def test_batch_equals_single_and_counts_evaluations(model, frame, rng):
    data, truth = frame
    for name, setup in setups(data, truth):
        energy = make_energy("cpu", model, setup)
        poses = perturbed(truth, rng, 9)
        batch = energy(poses)
        assert batch.shape == (9,) and batch.dtype == np.float64
        single = np.array([energy(p)[0] for p in poses])
        np.testing.assert_array_equal(batch, single, err_msg=name)
        assert energy.evaluations == 18


def test_energy_refuses_a_pose_of_the_wrong_length(model, frame):
    """The compiled kernel indexes 35 parameters without bounds checks: a short pose is refused."""
    data, truth = frame
    energy = CpuEnergy(model, data.full_setup(truth, half=True))
    with pytest.raises(ValueError, match="expected 35 parameters, got 34"):
        energy(truth[None, :34])


def test_a_window_counts_nothing_past_an_image_edge_the_silhouette_touches(model, frame, rng):
    """A limb's window reaching past an image's edge that the camera's silhouette touches counts
    the whole image's XOR inside it and nothing beyond: a body partly outside a camera's view is
    not pushed back into it (counted, a person walking out of one view was lost, every limb
    fitted away from the edge). Past edges the silhouette does not touch the body pays as
    outside the silhouette, as before: the energy with no open edges."""
    data, truth = frame
    whole = data.whole_image_energy()
    leg = CHAINS["right_leg"].segments
    all_open = np.ones((len(data.studio), 4), dtype=bool)
    crossed = 0
    for x in perturbed(truth, rng, 6, spread=0.2):
        x[0] += 1.1  # near the studio's edge: the legs past the bottom or side of some images
        for setup in (replace(data.window_setup(x, leg[:2], ARM_WINDOW, True), moving=leg),
                      data.window_setup(x, leg[2:], SMALL_WINDOW, False)):
            xor = whole.render(x) ^ data.masks
            inside = []
            for k, (cam, win) in enumerate(zip(setup.studio, setup.windows)):
                crossed += not (0 <= win.x0 and win.x0 + win.width <= cam.width
                                and 0 <= win.y0 and win.y0 + win.height <= cam.height)
                inside.append(xor[k, max(win.y0, 0):win.y0 + win.height, max(win.x0, 0):win.x0 + win.width].sum())
            expected = weighted(setup, inside)
            assert CpuEnergy(model, replace(setup, bounds=counted_bounds(data.studio, all_open)))(x)[0] == expected
            closed = CpuEnergy(model, replace(setup, bounds=None))
            shut = CpuEnergy(model, replace(setup, bounds=counted_bounds(data.studio, ~all_open)))
            assert shut(x)[0] == closed(x)[0] >= expected
            np.testing.assert_array_equal(shut.render(x), closed.render(x))
            # some edges open, some not: the byte windows (gl's, cameras of other sizes') as the row bits
            mixed = replace(setup, bounds=counted_bounds(data.studio, rng.random(all_open.shape) < 0.5))
            packed, byte = CpuEnergy(model, mixed), CpuEnergy(model, replace(mixed, inputs=mixed.input_windows,
                                                                               packed=None))
            poses = perturbed(x, rng, 4, spread=0.1)
            np.testing.assert_array_equal(packed(poses), byte(poses))
            np.testing.assert_array_equal(packed.render(x), byte.render(x))
    assert crossed  # some windows did reach past their images


def test_open_image_edges_are_those_the_silhouette_comes_near():
    """EDGE_RUN_PX pixels in a row within EDGE_TOUCH_PX of an edge, of each camera's own image
    in a padded stack, not specks; every edge of an empty silhouette (the body may be anywhere
    outside the image)."""
    from common.energy import EDGE_RUN_PX, EDGE_TOUCH_PX, open_image_edges

    masks = np.zeros((4, 60, 80), bool)
    masks[0, 0, 10:10 + EDGE_RUN_PX - 1] = masks[0, 1, 12 + EDGE_RUN_PX] = True  # specks on the top edge
    masks[0, 20:30, 30:40] = True                       # in the middle: no edge
    masks[1, 20:30, 80 - EDGE_TOUCH_PX:] = True          # at the right edge
    masks[1, 60 - EDGE_TOUCH_PX, 5:5 + EDGE_RUN_PX] = True  # and a run at the bottom
    masks[2, 10:20, 50 - EDGE_TOUCH_PX] = True          # at the right edge of a 50x40 camera
    masks[2, 40 - EDGE_TOUCH_PX - 1, 10:20] = True       # one row short of its bottom edge
    edges = open_image_edges(masks, [(80, 60), (80, 60), (50, 40), (80, 60)])
    np.testing.assert_array_equal(edges, [[False, False, False, False], [False, False, True, True],
                                          [False, False, True, False], [True, True, True, True]])


def test_prerendered_equals_full_render_in_the_same_window(model, frame, rng):
    """Pre-rendering the parts that do not move changes the cost, not the value."""
    data, truth = frame
    for chain, size in (("left_arm", ARM_WINDOW), ("right_leg", ARM_WINDOW), ("head", SMALL_WINDOW)):
        segs = CHAINS[chain].segments
        centre = segs[:2] if chain != "head" else segs
        setup = replace(data.window_setup(truth, centre, size, True), moving=segs)
        pre = CpuEnergy(model, setup)
        full = CpuEnergy(model, replace(setup, prerender=False))
        assert pre.static_mask.any()  # the torso is in the window and was pre-rendered
        poses = perturbed(truth, rng, 12, spread=0.3, indices=CHAINS[chain].params)
        np.testing.assert_array_equal(pre(poses), full(poses), err_msg=chain)


def test_prerendered_parts_stay_where_they_were_rendered(model, frame):
    """Moving a pre-rendered (static) part does not change the pre-rendered energy: the
    equality above is not an accident of both renders moving everything."""
    data, truth = frame
    segs = CHAINS["left_arm"].segments
    setup = replace(data.window_setup(truth, segs[:2], ARM_WINDOW, True), moving=segs)
    pre, full = CpuEnergy(model, setup), CpuEnergy(model, replace(setup, prerender=False))
    moved = truth.copy()
    moved[0] += 0.05  # the root (torso) moves; the arm goes with it
    assert pre(truth)[0] == full(truth)[0]
    assert pre(moved)[0] != full(moved)[0]


def test_compiled_powell_takes_the_same_steps_as_optimize_powell(model, frame, rng):
    """``fitting.powell`` runs the compiled twin (``common.powell_cpu``) on the cpu energy and
    ``optimize.powell`` on any other callable: the same poses, objectives, evaluation counts
    and iterations, for a limb in its window (also with line searches refined down to 1e-9,
    the most probes a line search makes), the torso with its limbs held and the spine prior
    (half resolution), and all 35 parameters with the prior (a hop)."""
    from common.body import P
    from common.fitting import FitOptions, powell
    from common.objective import HeldLimbs, SpinePrior

    data, truth = frame
    options = FitOptions()
    arm = CHAINS["left_arm"]
    arm_setup = replace(data.window_setup(truth, arm.segments[:2], ARM_WINDOW, True), moving=arm.segments)
    torso_energy = CpuEnergy(model, data.full_setup(truth, half=True))
    hold = HeldLimbs(model, forward_kinematics(model, truth).rotations[0])
    every = np.arange(PARAM_COUNT)
    cases = [  # name, objective, indices, steps, completion, budget, line-search resolution
        ("arm", CpuEnergy(model, arm_setup), arm.params[:4], np.full(4, 0.2), None, 400, options.xtol),
        # the most probes a line search makes: refined down to 1e-9
        ("arm, fine", CpuEnergy(model, arm_setup), arm.params[:4], np.full(4, 0.2), None, 400, 1e-9),
        ("torso", SpinePrior(torso_energy, 1500.0), CHAINS["torso"].params, np.array([0.03] * 3 + [0.1] * 6), hold,
         600, options.xtol),
        ("hop", SpinePrior(CpuEnergy(model, data.full_setup(truth)), 1500.0), every,
         np.where(every < 3, 0.03, 0.1), None, 300, options.xtol),
    ]
    for name, energy, idx, steps, complete, budget, xtol in cases:
        start = perturbed(truth, rng, 1, spread=0.2, indices=idx)[0]
        if isinstance(energy, SpinePrior):
            start[P["spine_z"]] = 0.1  # the prior pulls
            plain = SpinePrior(lambda p, e=energy.energy: e(p), energy.weight)
        else:
            plain = (lambda p, e=energy: e(p))
        compiled = powell(energy, start, idx, steps, replace(options, xtol=xtol), budget, complete=complete)
        reference = powell(plain, start, idx, steps, replace(options, xtol=xtol), budget, complete=complete)
        np.testing.assert_array_equal(compiled[0], reference[0], err_msg=name)
        assert compiled[1:] == reference[1:], name
        assert compiled[1] < float(plain(start[None])[0]), name  # it did move downhill
    assert cases[0][1].evaluations > 0  # the compiled solve counts its evaluations


def test_compiled_powell_refuses_shapes_its_loops_would_read_past(model, frame):
    """The compiled loops index without bounds checks: a short pose, steps that do not match the
    indices, an index past 35, held rotations of the wrong shape and a line-search resolution
    (xtol) that is not positive, which sizes the probes' arrays, are refused."""
    from common.powell_cpu import powell_cpu

    data, truth = frame
    energy = CpuEnergy(model, data.full_setup(truth, half=True))
    for x0, idx, steps, hold, message in (
            (truth[:34], [0, 1], [0.1, 0.1], None, "expected 35 parameters"),
            (truth, [0, 1], [0.1, 0.1, 0.1], None, "do not match"),
            (truth, [0, 35], [0.1, 0.1], None, "do not match"),
            (truth, [0, 1], [0.1, 0.1], np.eye(3), r"\(16, 3, 3\)")):
        with pytest.raises(ValueError, match=message):
            powell_cpu(energy, x0, idx, np.array(steps), 0.02, 1e-4, 50, hold_rotations=hold)
    for xtol in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="xtol must be positive"):
            powell_cpu(energy, truth, [0, 1], np.array([0.1, 0.1]), xtol, 1e-4, 50)
    assert energy.evaluations == 0


def test_the_kernel_cache_is_keyed_by_every_file_with_cached_kernels():
    """numba checks a cached kernel against its own file only; the cache folder is named by a
    hash of KERNEL_SOURCES, so every file with cached kernels must be among them."""
    from pathlib import Path

    import common

    here = Path(common.__file__).parent
    cached = {p.name for p in here.glob("*.py") if "cache=True" in p.read_text()}
    assert cached and cached <= set(common.KERNEL_SOURCES)
    assert "optimize.py" in common.KERNEL_SOURCES  # the compiled Powell's constants


def test_make_energy_rejects_unknown_backend(model, frame):
    data, truth = frame
    with pytest.raises(ValueError, match="nope"):
        make_energy("nope", model, data.full_setup(truth))


# ------------------------------------------------------------- analytic vs tessellated

def unit_sphere(n_lon: int, n_lat: int) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere: (V, 3) vertices on the unit sphere, (T, 3) outward-wound triangles."""
    theta = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    phi = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.sin(theta), np.sin(phi)),
                     np.repeat(np.cos(theta)[:, None], n_lon, axis=1)], axis=-1).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    j = np.arange(n_lon)
    nxt = (j + 1) % n_lon
    tris = [np.stack([np.zeros(n_lon, int), 1 + j, 1 + nxt], 1)]
    for i in range(n_lat - 2):
        a, b = 1 + i * n_lon + j, 1 + i * n_lon + nxt
        tris += [np.stack([a, a + n_lon, b], 1), np.stack([b, a + n_lon, b + n_lon], 1)]
    last, base = len(verts) - 1, 1 + (n_lat - 2) * n_lon
    tris.append(np.stack([np.full(n_lon, last), base + nxt, base + j], 1))
    return verts, np.concatenate(tris)


def ellipsoid_mesh(model, params: np.ndarray, sphere) -> tuple[np.ndarray, np.ndarray]:
    """The model's 16 posed ellipsoids as one triangle mesh: (V, 3) world vertices, (T, 3)."""
    u, tri = sphere
    pose = forward_kinematics(model, params)
    centres, A = ellipsoid_world(model, pose.rotations, pose.origins, range(16))
    verts = (np.einsum("sij,vj->svi", A[0], u) + centres[0][:, None]).reshape(-1, 3)
    tris = (tri[None] + len(u) * np.arange(16)[:, None, None]).reshape(-1, 3)
    return verts, tris


def test_unit_sphere_mesh_is_closed():
    verts, tris = unit_sphere(*SPHERE_SEGMENTS)
    np.testing.assert_allclose(np.linalg.norm(verts, axis=1), 1.0)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # every edge shared by exactly two triangles


def test_analytic_ellipsoids_match_a_tessellated_mesh(model):
    from common.render_gl import MeshRenderer

    studio = circle_studio(8, 320, 240)
    rng = np.random.default_rng(7)
    sphere = unit_sphere(*SPHERE_SEGMENTS)
    base = rest_params(model)
    base[0:2] = 0.0
    renderer = None
    for trial in range(3):
        p = perturbed(base, rng, 1, spread=0.4)[0] if trial else base
        verts, tris = ellipsoid_mesh(model, p, sphere)
        if renderer is None:
            renderer = MeshRenderer(studio, tris)
        mesh = np.stack(renderer.render_masks(verts))
        windows = tuple(Window(0, 0, c.width, c.height) for c in studio)
        energy = CpuEnergy(model, EnergySetup(studio, windows, mesh, tuple(range(16)), p, prerender=False))
        analytic = energy.render(p)
        union = np.count_nonzero(analytic | mesh)
        mismatch = np.count_nonzero(analytic ^ mesh)
        assert union > 8 * 2000  # the body is in view of every camera
        assert mismatch / union < MESH_MISMATCH, (trial, mismatch, union)
        assert int(energy(p)[0]) == mismatch
        # and the comparison can fail: ellipsoids 5% too fat differ by more than the bound
        fat = EnergySetup(studio, windows, mesh, tuple(range(16)), p, prerender=False)
        fat_model = replace(model, ellipsoid_radii=model.ellipsoid_radii * 1.05)
        assert int(CpuEnergy(fat_model, fat)(p)[0]) / union > MESH_MISMATCH


def test_fitting_undistorts_so_analytic_ellipsoids_follow_lens_distortion(model):
    """Distorted cameras: FrameData resamples the silhouettes into ideal pinhole images, where
    the analytic (pinhole) ellipsoids match the distorted render as well as without distortion."""
    from common.camera import Studio
    from common.fitting import FrameData
    from common.render_gl import MeshRenderer

    studio = Studio(tuple(replace(c, dist=np.array([-0.2, 0.0, 0.0, 0.0, 0.0])) for c in circle_studio(8, 320, 240)))
    p = rest_params(model)
    p[0:2] = 0.0
    verts, tris = ellipsoid_mesh(model, p, unit_sphere(*SPHERE_SEGMENTS))
    distorted = np.stack(MeshRenderer(studio, tris).render_masks(verts))
    frame = FrameData(model, studio, distorted)
    assert not any(c.has_distortion for c in frame.studio)
    mesh = frame.masks
    analytic = CpuEnergy(model, frame.full_setup(p)).render(p)
    # nearest-pixel resampling moves edges by up to half a pixel: ~2.1% measured
    assert np.count_nonzero(analytic ^ mesh) / np.count_nonzero(analytic | mesh) < RESAMPLED_MISMATCH
    # without the resampling the mismatch is ~3.5% (k1 = -0.2)
    assert np.count_nonzero(analytic ^ distorted) / np.count_nonzero(analytic | distorted) > RESAMPLED_MISMATCH


# ------------------------------------------------------------------ volume energy (Bottino)

def test_surface_distances_agree_with_the_closest_point_near_the_surface(model):
    """The first-order distance the volume energy uses, against Newton's exact closest point."""
    from common.ellipsoid_fit import segment_ellipsoids, shell_distances
    from common.energy import surface_distances

    rng = np.random.default_rng(3)
    centres, axes, radii = segment_ellipsoids(model, rest_params(model))
    # points within 2 cm of each ellipsoid's surface, inside and out
    directions = rng.normal(size=(16, 200, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    surface = centres[:, None] + np.einsum("sij,snj->sni", axes, directions * radii[:, None])
    points = (surface + rng.uniform(-0.02, 0.02, (16, 200, 1)) * directions).reshape(-1, 3)
    exact = shell_distances(points, centres, axes, radii).T           # (16, n)
    approx = surface_distances(points, centres, axes, radii)
    own = np.repeat(np.arange(16), 200)
    err_mm = np.abs(approx - exact)[own, np.arange(len(points))] * 1000
    assert np.median(err_mm) < 0.5 and np.percentile(err_mm, 95) < 3.0, (np.median(err_mm), err_mm.max())


def test_volume_energy_prefers_the_truth_and_measures_static_parts_once(model, frame):
    from common.energy import VolumeEnergy

    data, truth = frame
    points = data.surface_points
    assert len(points) > 100
    full = VolumeEnergy(model, replace(data.full_setup(truth), volume_points=points))
    rng = np.random.default_rng(4)
    others = perturbed(truth, rng, 16, spread=0.3)
    assert full(truth)[0] < full(others).min()
    arm = CHAINS["left_arm"]
    limb = VolumeEnergy(model, replace(data.full_setup(truth), volume_points=points, moving=arm.segments,
                                       prerender=True))
    moved = perturbed(truth, rng, 8, spread=0.5, indices=arm.params)
    np.testing.assert_allclose(limb(moved), full(moved), rtol=1e-12)


def test_whole_image_energy_is_built_once_per_frame_and_resolution(model, frame, rng):
    """It pre-renders nothing, so one energy serves every pose of the frame."""
    data, truth = frame
    poses = perturbed(truth, rng, 5)
    for half in (False, True):
        whole = data.whole_image_energy(half)
        assert data.whole_image_energy(half) is whole
        fresh = CpuEnergy(model, data.full_setup(poses[0], half=half))
        np.testing.assert_array_equal(whole(poses), fresh(poses))
    assert data.whole_image_energy(True) is not data.whole_image_energy(False)


@pytest.mark.parametrize("shape", [(3, 16, 128), (2, 9, 72), (2, 5, 70), (1, 3, 8)])
def test_xor_bits_masks_pixel_by_pixel(shape):
    """The static-and-input bit masks, read 8 pixels at a time (a row of 70 padded to 72),
    against their definition, bit by bit."""
    from common.conic_bits import xor_bits

    rng = np.random.default_rng(shape[2])
    static, inputs = rng.random(shape) < 0.3, rng.random(shape) < 0.4
    gain, loss, base = xor_bits(static, inputs)
    columns = np.arange(shape[2])

    def bits(words):  # (K, h, words) uint64 -> (K, h, w) bool, bit c % 64 of word c // 64
        return ((words[..., columns // 64] >> (columns % 64).astype(np.uint64)) & np.uint64(1)).astype(bool)

    np.testing.assert_array_equal(bits(gain), ~static & ~inputs)
    np.testing.assert_array_equal(bits(loss), ~static & inputs)
    assert gain.shape == loss.shape == (*shape[:2], (shape[2] + 63) // 64)
    np.testing.assert_array_equal(base, np.count_nonzero(static != inputs, axis=(1, 2)))
    # the bits past the last column are clear, so a span reaching the word's end adds nothing
    spare = (-shape[2]) % 64
    if spare:
        assert not np.any(gain[..., -1] >> np.uint64(64 - spare)) and not np.any(loss[..., -1] >> np.uint64(64 - spare))


def _cut(masks: np.ndarray, x0: np.ndarray, y0: np.ndarray, rows: int, width: int) -> np.ndarray:
    """Windows cut from masks by slicing, clear outside the images (the definition)."""
    K, H, W = masks.shape
    out = np.zeros((K, rows, width), bool)
    for k in range(K):
        xs, ys, xe, ye = max(x0[k], 0), max(y0[k], 0), min(x0[k] + width, W), min(y0[k] + rows, H)
        if xs < xe and ys < ye:
            out[k, ys - y0[k]:ye - y0[k], xs - x0[k]:xe - x0[k]] = masks[k, ys:ye, xs:xe]
    return out


@pytest.mark.parametrize("seed", range(6))
def test_windows_cut_from_row_bits(seed):
    """Windows of any size at any corner (off every edge too) cut from the packed rows are the
    sliced windows, pixel by pixel."""
    from common.conic_bits import cut_windows, pack_rows

    rng = np.random.default_rng(seed)
    K, H, W = 3, int(rng.integers(20, 200)), int(rng.integers(20, 200))
    masks = rng.random((K, H, W)) < 0.4
    rows, width = int(rng.integers(1, 150)), int(rng.integers(1, 150))
    x0, y0 = rng.integers(-160, W + 20, K), rng.integers(-160, H + 20, K)
    np.testing.assert_array_equal(cut_windows(pack_rows(masks), x0, y0, rows, width), _cut(masks, x0, y0, rows, width))


def test_value_bits_from_row_bits_equal_the_byte_windows(model, frame, rng):
    """An energy whose windows are cut from the frame's row bits (limb, extremity and odd-sized
    windows, the whole images) has the bit masks, base and energies of the same energy built
    from byte windows."""
    data, truth = frame
    arm, leg = CHAINS["left_arm"].segments, CHAINS["right_leg"].segments
    for k, x in enumerate(perturbed(truth, rng, 6, spread=0.4)):
        x = x.copy()
        x[:2] += 0.6 * (k % 2)  # the body moved off, its windows past the images' edges
        built = [replace(data.window_setup(x, arm[:2], ARM_WINDOW, True), moving=arm),
                 data.window_setup(x, leg[2:], SMALL_WINDOW, k % 3 == 0),
                 data.window_setup(x, CHAINS["head"].segments, 100, True),
                 replace(data.full_setup(x, half=k % 2 == 1), moving=leg, prerender=True)]
        for setup in built:
            assert setup.packed is not None
            fast = CpuEnergy(model, setup)
            masks = data.half_masks if setup.studio is data.half_studio else data.masks
            cut = _cut(masks, *window_origins(setup.windows), setup.windows[0].height, setup.windows[0].width)
            plain = CpuEnergy(model, replace(setup, inputs=cut, packed=None))
            np.testing.assert_array_equal(fast.gain, plain.gain)
            np.testing.assert_array_equal(fast.loss, plain.loss)
            assert fast.base == plain.base
            poses = perturbed(x, rng, 8)
            np.testing.assert_array_equal(fast(poses), plain(poses))
            np.testing.assert_array_equal(fast.render(x), plain.render(x))


def _ellipse(cx: float, cy: float, a: float, b: float, angle: float) -> np.ndarray:
    """(3, 3) conic of an ellipse centred at (cx, cy) with half-axes a, b, negative inside."""
    R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    M = R @ np.diag([1 / a ** 2, 1 / b ** 2]) @ R.T
    c = np.array([cx, cy])
    Q = np.zeros((3, 3))
    Q[:2, :2], Q[:2, 2], Q[2, :2], Q[2, 2] = M, -M @ c, -M @ c, c @ M @ c - 1
    return Q


@pytest.mark.parametrize("seed", range(40))
def test_value_bits_from_row_bits_equal_those_of_byte_windows(seed):
    """window_value_bits against its definition, xor_bits of the still parts' coverage and the
    sliced windows: random masks, 0-3 still ellipses (some not drawable, some covering many
    words), corners off every edge, windows wider and taller than the image, widths that are not
    a multiple of 64, pixels counted only inside random bounds (some unbounded, some within the
    window); and cut_windows against the sliced windows."""
    from common.conic_bits import conic_coverage, cut_windows, pack_rows, window_value_bits, xor_bits

    rng = np.random.default_rng(seed)
    K, H, W = int(rng.integers(1, 4)), int(rng.integers(1, 200)), int(rng.integers(1, 260))
    masks = rng.random((K, H, W)) < rng.random()
    rows, width = int(rng.integers(1, 200)), int(rng.integers(1, 300))
    x0, y0 = rng.integers(-350, W + 80, K), rng.integers(-250, H + 80, K)
    S = int(rng.integers(0, 4))
    C, drawable = np.zeros((1, K, S, 3, 3)), rng.random((1, K, S)) < 0.85
    for k in range(K):
        for s in range(S):
            C[0, k, s] = rng.uniform(0.1, 10) * _ellipse(
                x0[k] + rng.uniform(-50, width + 50), y0[k] + rng.uniform(-50, rows + 50),
                rng.uniform(0.3, 120), rng.uniform(0.3, 120), rng.uniform(0, np.pi))
    far = 1 << 30
    lows = [rng.choice([-far, 0, int(rng.integers(-100, n))], K) for n in (W, H)]
    highs = [rng.choice([far, n, int(rng.integers(0, n + 100))], K) for n in (W, H)]
    bounds = np.stack([*lows, *highs], axis=1).astype(np.int64)  # x_lo, y_lo, x_hi, y_hi
    packed = pack_rows(masks)
    gain, loss, base = window_value_bits(packed, x0, y0, rows, width, C, drawable, bounds)
    still = conic_coverage(C, drawable, y0.astype(float), x0.astype(float), rows, width)[0]
    # a pixel not counted is worth nothing: still part and silhouette both set there
    ys, xs = y0[:, None] + np.arange(rows), x0[:, None] + np.arange(width)
    beyond = ~(((ys >= bounds[:, 1, None]) & (ys < bounds[:, 3, None]))[:, :, None]
               & ((xs >= bounds[:, 0, None]) & (xs < bounds[:, 2, None]))[:, None, :])
    expected = xor_bits(still | beyond, _cut(masks, x0, y0, rows, width) | beyond)
    np.testing.assert_array_equal(gain, expected[0])
    np.testing.assert_array_equal(loss, expected[1])
    np.testing.assert_array_equal(base, expected[2])
    np.testing.assert_array_equal(cut_windows(packed, x0, y0, rows, width), _cut(masks, x0, y0, rows, width))


def test_setups_cut_from_packed_rows_are_checked(model, frame):
    data, truth = frame
    setup = data.window_setup(truth, CHAINS["head"].segments, SMALL_WINDOW, True)
    with pytest.raises(ValueError, match="as many windows"):
        replace(setup, windows=setup.windows[:-1])
    with pytest.raises(ValueError, match="one size"):
        replace(setup, windows=(Window(0, 0, 32, 32),) + setup.windows[1:])
    with pytest.raises(ValueError, match="needs its input windows"):
        replace(setup, packed=None)


def test_cameras_count_no_more_than_the_median_camera_sees_the_body():
    """``camera_weights``: a camera that sees the body at s > FULL_WEIGHT_SCALE times the median
    camera's scale (nearer, or a longer focal length) counts (FULL_WEIGHT_SCALE / s)^2 per
    pixel, the others 1; weights are multiples of WEIGHT_STEP (exact sums); no centre, no
    weights."""
    from common.camera import Studio
    from common.energy import FULL_WEIGHT_SCALE, WEIGHT_STEP, camera_weights

    studio = circle_studio(8, 320, 240, radius=3.0, overhead=False)
    middle = np.array([0.0, 0.0, 0.9])  # where every camera looks
    np.testing.assert_array_equal(camera_weights(studio, middle), np.ones(8))
    assert camera_weights(studio, None) is None
    near = middle + 0.7 * (studio.cameras[0].center - middle)  # most of the way to camera 0
    weights = camera_weights(studio, near)
    depth = np.array([(c.R @ near + c.t)[2] for c in studio.cameras])
    expected = np.minimum(1.0, (FULL_WEIGHT_SCALE * depth / np.median(depth)) ** 2)
    np.testing.assert_allclose(weights, expected, atol=WEIGHT_STEP / 2)
    assert weights[0] < 0.5 and weights.max() == 1.0
    assert np.all(weights / WEIGHT_STEP == np.round(weights / WEIGHT_STEP))
    # a sharper camera at the same distance: three times the focal length, (1.5 / 3)^2 the worth
    cams = list(studio.cameras)
    cams[3] = replace(cams[3], K=cams[3].K * np.array([[3, 1, 1], [1, 3, 1], [1, 1, 1]]))
    np.testing.assert_array_equal(camera_weights(Studio(tuple(cams), studio.source), middle),
                                  [1, 1, 1, (FULL_WEIGHT_SCALE / 3) ** 2, 1, 1, 1, 1])
