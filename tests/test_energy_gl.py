"""The gl energy backend: agreement with the cpu backend, exact XOR counts, batching, mesh fits."""
import numpy as np
import pytest

from common.body import (CHAINS, PARAM_COUNT, clip_to_limits, forward_kinematics, load_body_model, rest_params,
                         rigid_vertices)
from common.camera import circle_studio
from common.energy import ARM_WINDOW, CpuEnergy, EnergySetup, Window, ellipsoid_world
from common.objective import make_energy
from common.errors import UserError

ARM = CHAINS["left_arm"]
ALL = tuple(range(16))
AGREEMENT = 0.01  # |E_gl - E_cpu| over the rendered silhouette's pixels, ellipsoid surface


@pytest.fixture(scope="module")
def ctx():
    from common.render_gl import gl_context

    try:
        return gl_context()
    except UserError as exc:
        pytest.skip(f"no headless OpenGL: {exc}")


@pytest.fixture(scope="module")
def model():
    return load_body_model()


@pytest.fixture(scope="module")
def studio():
    return circle_studio(8, 320, 240)


def random_pose(model, rng, spread=0.25):
    p = rest_params(model, heading=rng.uniform(-np.pi, np.pi))
    p[4:] += rng.normal(0.0, spread, PARAM_COUNT - 4)
    p[4:6] *= 0.3  # keep the actor roughly upright
    return clip_to_limits(p)


def mesh_masks(model, studio, params):
    """(K, H, W) bool silhouettes of the rigid mesh, rendered by the plain renderer."""
    from common.render_gl import MeshRenderer

    verts = rigid_vertices(model, forward_kinematics(model, params))
    return np.stack(MeshRenderer(studio, model.triangles).render_masks(verts))


def part_windows(model, studio, params, segments, size):
    """Windows of ``size`` pixels centred on the projected mean of the segments' ellipsoids."""
    pose = forward_kinematics(model, params)
    centre = ellipsoid_world(model, pose.rotations, pose.origins, segments)[0][0].mean(axis=0)
    corners = [np.floor(cam.project(centre[None])[0] - size / 2 + 0.5).astype(int) for cam in studio]
    return tuple(Window(int(x0), int(y0), size, size) for x0, y0 in corners)


def cut_window(mask, w: Window) -> np.ndarray:
    """(H, W) bool image -> (w.height, w.width) bool, zeros outside the image."""
    H, W = mask.shape
    out = np.zeros((w.height, w.width), dtype=bool)
    xs, ys = max(w.x0, 0), max(w.y0, 0)
    xe, ye = min(w.x0 + w.width, W), min(w.y0 + w.height, H)
    if xs < xe and ys < ye:
        out[ys - w.y0:ye - w.y0, xs - w.x0:xe - w.x0] = mask[ys:ye, xs:xe]
    return out


def make_setup(studio, masks, windows, moving, params, prerender):
    inputs = np.stack([cut_window(m, w) for m, w in zip(masks, windows)])
    return EnergySetup(studio, windows, inputs, tuple(moving), np.asarray(params), prerender)


def full_windows(studio):
    return tuple(Window(0, 0, cam.width, cam.height) for cam in studio)


def perturbed(params, rng, indices, spread, count):
    """(count + 1, 35): params itself, then ``count`` perturbations of ``indices``."""
    out = np.repeat(params[None], count + 1, axis=0)
    out[1:, list(indices)] += rng.normal(0.0, spread, (count, len(indices)))
    return clip_to_limits(out)


def assert_agrees_with_cpu(gl, cpu, candidates):
    e_gl, e_cpu = gl(candidates), cpu(candidates)
    silhouette = np.array([cpu.render(p).sum() for p in candidates])
    assert np.all(silhouette > 0)
    worst = np.max(np.abs(e_gl - e_cpu) / silhouette)
    assert worst < AGREEMENT, (e_gl, e_cpu, silhouette)
    static = np.count_nonzero(gl.static_mask ^ cpu.static_mask)
    assert static <= AGREEMENT * max(1, cpu.static_mask.sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ellipsoids_agree_with_cpu_in_arm_windows_with_prerendering(ctx, model, studio, seed):
    from common.energy_gl import GlEnergy

    rng = np.random.default_rng(seed)
    p = random_pose(model, rng)
    windows = part_windows(model, studio, p, ARM.segments, ARM_WINDOW)
    setup = make_setup(studio, mesh_masks(model, studio, p), windows, ARM.segments, p, prerender=True)
    gl = GlEnergy(model, setup, surface="ellipsoid")
    assert_agrees_with_cpu(gl, CpuEnergy(model, setup), perturbed(p, rng, ARM.params, 0.3, 7))
    assert ctx.error == "GL_NO_ERROR"


@pytest.mark.parametrize("seed, scale", [(3, 1.0), (4, 1.0), (5, 0.5)])
def test_ellipsoids_agree_with_cpu_on_whole_images(ctx, model, studio, seed, scale):
    from common.energy_gl import GlEnergy

    rng = np.random.default_rng(seed)
    cams = studio.scaled(scale) if scale != 1.0 else studio
    p = random_pose(model, rng)
    setup = make_setup(cams, mesh_masks(model, cams, p), full_windows(cams), ARM.segments, p, prerender=False)
    gl = GlEnergy(model, setup, surface="ellipsoid")
    assert gl.static_mask.sum() == 0  # no pre-rendering: everything moves
    assert_agrees_with_cpu(gl, CpuEnergy(model, setup), perturbed(p, rng, range(PARAM_COUNT), 0.08, 5))
    assert ctx.error == "GL_NO_ERROR"


def test_windows_past_the_image_edges_and_cutting_the_body(ctx, model, studio):
    """Geometry outside a window must not leak into the neighbouring tiles of the atlas."""
    from common.energy_gl import GlEnergy

    rng = np.random.default_rng(6)
    p = random_pose(model, rng)
    centred = part_windows(model, studio, p, ALL, 96)
    shifts = rng.integers(-90, 91, size=(len(studio), 2))
    windows = tuple(Window(w.x0 + int(dx), w.y0 + int(dy), 96, 96) for w, (dx, dy) in zip(centred, shifts))
    setup = make_setup(studio, mesh_masks(model, studio, p), windows, ARM.segments, p, prerender=True)
    gl = GlEnergy(model, setup, surface="ellipsoid")
    assert_agrees_with_cpu(gl, CpuEnergy(model, setup), perturbed(p, rng, range(PARAM_COUNT), 0.1, 5))


@pytest.mark.parametrize("surface", ["ellipsoid", "mesh"])
def test_energy_is_the_xor_count_of_the_render_batched_or_not(ctx, model, studio, surface):
    from common.energy_gl import GlEnergy

    rng = np.random.default_rng(7)
    p = random_pose(model, rng)
    windows = part_windows(model, studio, p, ARM.segments, ARM_WINDOW)
    setup = make_setup(studio, mesh_masks(model, studio, p), windows, ARM.segments, p, prerender=True)
    gl = GlEnergy(model, setup, surface=surface)
    candidates = perturbed(p, rng, ARM.params, 0.4, 4)
    expected = np.array([np.count_nonzero(gl.render(c) ^ setup.inputs) for c in candidates])
    np.testing.assert_array_equal(gl(candidates), expected)
    np.testing.assert_array_equal([gl(c)[0] for c in candidates], expected)
    gl.chunk_poses = 2  # several draws, one read
    np.testing.assert_array_equal(gl(candidates), expected)
    assert ctx.error == "GL_NO_ERROR"


def test_mesh_energy_is_zero_at_the_true_pose_and_grows_away_from_it(ctx, model, studio):
    from common.energy_gl import GlEnergy

    rng = np.random.default_rng(8)
    p = random_pose(model, rng)
    masks = mesh_masks(model, studio, p)
    windows = part_windows(model, studio, p, ARM.segments, ARM_WINDOW)
    arm = GlEnergy(model, make_setup(studio, masks, windows, ARM.segments, p, prerender=True), surface="mesh")
    silhouette = np.count_nonzero(arm.render(p))
    assert arm(p)[0] <= 0.001 * silhouette
    means = [arm(perturbed(p, rng, ARM.params, spread, 6)[1:]).mean() for spread in (0.05, 0.15, 0.4)]
    assert arm(p)[0] < means[0] < means[1] < means[2]

    whole = GlEnergy(model, make_setup(studio, masks, full_windows(studio), ALL, p, prerender=False), surface="mesh")
    assert whole(p)[0] <= 0.001 * masks.sum()
    assert whole(perturbed(p, rng, range(6, PARAM_COUNT), 0.2, 1)[1:])[0] > 0.02 * masks.sum()


def test_interface(ctx, model, studio):
    from common.energy_gl import GlEnergy

    p = rest_params(model)
    windows = part_windows(model, studio, p, CHAINS["head"].segments, 64)
    setup = make_setup(studio, mesh_masks(model, studio, p), windows, CHAINS["head"].segments, p, prerender=True)
    gl = make_energy("gl", model, setup)
    assert isinstance(gl, GlEnergy) and gl.backend == "gl" and gl.surface == "mesh"
    assert gl.renderer_name == ctx.info["GL_RENDERER"] and gl.renderer_name
    single = gl(p)
    assert single.shape == (1,) and single.dtype == np.float64
    assert gl(np.repeat(p[None], 3, axis=0)).shape == (3,)
    assert gl.evaluations == 4
    assert gl.render(p).shape == setup.input_windows.shape and gl.render(p).dtype == bool
    with pytest.raises(ValueError):
        GlEnergy(model, setup, surface="cylinders")


def test_energies_release_their_gl_objects_and_leave_the_context_usable(ctx, model, studio):
    from common.energy_gl import GlEnergy

    p = rest_params(model)
    windows = part_windows(model, studio, p, ARM.segments, ARM_WINDOW)
    setup = make_setup(studio, mesh_masks(model, studio, p), windows, ARM.segments, p, prerender=True)
    candidates = perturbed(p, np.random.default_rng(9), ARM.params, 0.3, 3)
    first = GlEnergy(model, setup, surface="ellipsoid")
    expected = first(candidates)
    del first  # garbage collection releases it
    for _ in range(3):
        gl = GlEnergy(model, setup, surface="ellipsoid")
        np.testing.assert_array_equal(gl(candidates), expected)
        gl.render(p)
        gl.release()
        gl.release()
        assert ctx.error == "GL_NO_ERROR"
    assert mesh_masks(model, studio, p).any() and ctx.error == "GL_NO_ERROR"


def test_fit_warns_that_a_software_renderer_makes_gl_slow(monkeypatch, capsys):
    """``--energy gl`` on Mesa llvmpipe ran a frame for many minutes without a word."""
    import common.render_gl as render_gl
    from server.commands.fit import warn_if_software_gl

    monkeypatch.setattr(render_gl, "gl_renderer_name", lambda: "llvmpipe (LLVM 15.0.6, 256 bits)")
    warn_if_software_gl("gl")
    err = capsys.readouterr().err
    assert err.startswith("warning: --energy gl:") and "llvmpipe" in err and "--energy cpu" in err
    warn_if_software_gl("cpu")
    monkeypatch.setattr(render_gl, "gl_renderer_name", lambda: "NVIDIA H200/PCIe/SSE2")
    warn_if_software_gl("gl")
    assert capsys.readouterr().err == ""
