"""SPOT voxel reconstruction (common/voxels.py) and the voxels / live commands."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from common.calibration import save_calibration
from common.camera import Studio, circle_studio, look_at
from common.errors import InputFileError, UserError
from common.sequence import write_mask_png, write_sequence_meta
from common.voxels import (SpotGrid, bench_voxels, corrupt, false_acceptance_probability,
                           false_rejection_probability, load_voxels, person_ellipsoids, render_ellipsoids,
                           save_voxels, surface_voxels)
from server.cli import main

SPHERE_CENTRE = np.array([0.05, -0.05, 1.0])
SPHERE_RADIUS = 0.5


@pytest.fixture(scope="module")
def studio5():
    return circle_studio(5, 320, 240)


@pytest.fixture(scope="module")
def sphere_masks(studio5):
    return render_ellipsoids(studio5, [SPHERE_CENTRE], [np.eye(3)], [[SPHERE_RADIUS] * 3])


def _inside_sphere(grid: SpotGrid) -> np.ndarray:
    return np.linalg.norm(grid.voxel_centres() - SPHERE_CENTRE, axis=-1) < SPHERE_RADIUS


def test_sphere_is_reconstructed(studio5, sphere_masks):
    grid = SpotGrid.build(studio5, grid=48, q=2)
    result = grid.reconstruct(sphere_masks)
    truth = _inside_sphere(grid)
    iou = (result.occupied & truth).sum() / (result.occupied | truth).sum()
    assert iou > 0.85
    assert result.occupied[truth].mean() > 0.99  # a visual hull contains the object
    assert result.surface is not None and result.surface.sum() < result.occupied.sum()


def test_coarse_pass_and_early_rejection_give_plain_spot(studio5, sphere_masks):
    """reconstruct() (block pass, camera order, compacted alive set) == every voxel tested in every camera."""
    grid = SpotGrid.build(studio5, grid=32, q=3, epsilon=0.6)
    assert grid.threshold == 2
    rng = np.random.default_rng(1)
    for masks in (sphere_masks, corrupt(sphere_masks, 0.1, 0.05, rng)):
        result = grid.reconstruct(masks)
        plain = (grid.sample_counts(masks) >= grid.threshold).all(axis=0)
        np.testing.assert_array_equal(result.occupied, plain)
        assert result.tests < len(studio5) * grid.q * grid.grid ** 3


def test_camera_that_does_not_see_the_volume_carves_nothing(studio5, sphere_masks):
    away = look_at("away", (0.0, 6.0, 1.5), (0.0, 12.0, 1.5), 320, 240)
    studio6 = Studio(tuple(studio5) + (away,))
    masks6 = np.concatenate([sphere_masks, np.zeros((1, 240, 320), dtype=bool)])
    five = SpotGrid.build(studio5, grid=24).reconstruct(sphere_masks).occupied
    six = SpotGrid.build(studio6, grid=24).reconstruct(masks6).occupied
    np.testing.assert_array_equal(five, six)


def test_surface_of_a_box_is_its_shell():
    occupied = np.zeros((20, 20, 20), dtype=bool)
    occupied[3:13, 5:11, 2:17] = True  # 10 x 6 x 15
    surface = surface_voxels(occupied)
    assert surface.sum() == 10 * 6 * 15 - 8 * 4 * 13
    np.testing.assert_array_equal(surface[4:12, 6:10, 3:16], False)
    full = np.ones((5, 5, 5), dtype=bool)  # the grid's edge counts as empty
    assert surface_voxels(full).sum() == 125 - 27
    assert not surface_voxels(np.zeros((4, 4, 4), dtype=bool)).any()


def test_surface_matches_a_brute_force_neighbour_count(studio5, sphere_masks):
    result = SpotGrid.build(studio5, grid=32).reconstruct(sphere_masks)
    occ = np.pad(result.occupied, 1)
    neighbours = sum(np.roll(occ, s, axis=a) for a in range(3) for s in (1, -1))[1:-1, 1:-1, 1:-1]
    np.testing.assert_array_equal(result.surface, result.occupied & (neighbours < 6))


@pytest.mark.parametrize("q", [1, 2, 3, 4])
def test_false_acceptance_and_rejection_follow_eq3_eq4(studio5, sphere_masks, q):
    """Silhouettes corrupted pixel by pixel: SPOT's FA and FR rates match Cheung's Eq. 3 and 4.

    Eq. 3 concerns voxels outside in every camera (all samples background), Eq. 4 voxels
    inside in every camera (all samples silhouette); both assume Q distinct pixels.
    """
    eta, xi, rounds = 0.25, 0.35, 12
    grid = SpotGrid.build(studio5, grid=40, q=q)
    counts = grid.sample_counts(sphere_masks)
    pixels = grid.sample_pixels()
    seen = (pixels >= 0).all(axis=(0, 1))
    distinct = np.ones_like(seen)
    for a in range(q):
        for b in range(a + 1, q):
            distinct &= (pixels[:, a] != pixels[:, b]).all(axis=0)
    inside = (counts == q).all(axis=0) & seen & distinct
    outside = (counts == 0).all(axis=0) & seen & distinct
    assert inside.sum() > 500 and outside.sum() > 20000
    rng = np.random.default_rng(q)
    fa, fr = [], []
    for _ in range(rounds):
        occupied = grid.reconstruct(corrupt(sphere_masks, eta, xi, rng), surface=False).occupied
        fa.append(occupied[outside].mean())
        fr.append(1.0 - occupied[inside].mean())
    K = len(studio5)
    for measured, expected, trials in ((fa, false_acceptance_probability(xi, q, K), outside.sum()),
                                       (fr, false_rejection_probability(eta, q, K), inside.sum())):
        # Voxels share pixels, so rounds (not voxels) are the independent samples.
        sem = np.std(measured, ddof=1) / np.sqrt(rounds)
        binomial = np.sqrt(expected * (1 - expected) / (trials * rounds))
        assert abs(np.mean(measured) - expected) < 4.0 * max(sem, binomial), (q, np.mean(measured), expected)


def test_error_probabilities_match_the_paper():
    # Section 6: Q = 2, K = 5, eta = 0.043, xi = 0.021 -> FR 0.0092, FA 1.239e-7.
    assert false_rejection_probability(0.043, 2, 5) == pytest.approx(0.0092, abs=5e-5)
    assert false_acceptance_probability(0.021, 2, 5) == pytest.approx(1.239e-7, rel=1e-3)
    assert false_rejection_probability(0.3, 3, 4) == pytest.approx(1 - (1 - 0.3 ** 3) ** 4)


def test_person_reconstruction_keeps_the_limbs():
    studio = circle_studio(8, 320, 240)
    masks = render_ellipsoids(studio, *person_ellipsoids(arm_raise=0.6))
    result = SpotGrid.build(studio, grid=64).reconstruct(masks)
    pts = result.centres(result.occupied)
    assert pts[:, 0].min() < -0.45 and pts[:, 0].max() > 0.45  # hands
    assert pts[:, 2].max() > 1.65 and pts[:, 2].min() < 0.06  # head top, feet
    np.testing.assert_allclose(result.surface_points(), result.centres(result.surface.copy()))


def test_bad_input_is_refused(studio5, sphere_masks):
    with pytest.raises(UserError, match="masks"):
        SpotGrid.build(studio5, grid=16).reconstruct(sphere_masks[:, :100])
    with pytest.raises(UserError, match="q"):
        SpotGrid.build(studio5, grid=16, q=0)
    with pytest.raises(UserError, match="grid"):
        SpotGrid.build(studio5, grid=1)
    with pytest.raises(UserError, match="epsilon"):
        SpotGrid.build(studio5, grid=16, epsilon=1.5)
    with pytest.raises(UserError, match="bounds"):
        SpotGrid.build(studio5, grid=16, bounds=[[0, 0, 0], [1, -1, 1]])


def test_voxel_files_round_trip(tmp_path, studio5, sphere_masks):
    result = SpotGrid.build(studio5, grid=24).reconstruct(sphere_masks)
    save_voxels(tmp_path / "f.npz", result, frame=7)
    back = load_voxels(tmp_path / "f.npz")
    np.testing.assert_array_equal(back.occupied, result.occupied)
    np.testing.assert_array_equal(back.surface, result.surface)
    np.testing.assert_allclose(back.voxel_size, result.voxel_size)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputFileError):
        load_voxels(tmp_path / "bad.npz")
    with pytest.raises(InputFileError, match="missing"):
        load_voxels(tmp_path / "none.npz")


def test_bench_rows_have_the_agreed_keys():
    rows = bench_voxels(configs=((16, 5),), width=160, height=120)
    assert set(rows[0]) >= {"grid", "cameras", "q", "frames_per_second", "surface_frames_per_second"}
    assert rows[0]["frames_per_second"] > 0 and rows[0]["occupied"] > 0


# ---------------------------------------------------------------------------- commands

@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """A two-frame, five-camera silhouette sequence of the synthetic person."""
    root = tmp_path_factory.mktemp("seq")
    studio = circle_studio(5, 160, 120)
    save_calibration(studio, root / "calibration.json")
    for frame, raise_ in ((0, 0.5), (1, 0.7)):
        masks = render_ellipsoids(studio, *person_ellipsoids(arm_raise=raise_))
        for cam, mask in zip(studio, masks):
            write_mask_png(root / "silhouettes" / cam.name / f"{frame:06d}.png", mask)
    write_sequence_meta(root, [0, 1], 30.0, studio.names)
    return root


def test_voxels_command_writes_voxels_and_pictures(tmp_path, sequence, capsys):
    out = tmp_path / "out"
    assert main(["voxels", str(sequence), "--out", str(out), "--grid", "32", "--q", "2"]) == 0
    summary = json.loads((out / "voxels.json").read_text())
    assert summary["grid"] == 32 and len(summary["frames"]) == 2
    result = load_voxels(out / "voxels" / "000001.npz")
    assert result.occupied.shape == (32, 32, 32) and result.surface.sum() > 50
    assert result.surface.sum() == summary["frames"][1]["surface"]
    with Image.open(out / "pictures" / "000000.png") as im:
        assert im.size[0] == 3 * im.size[1]
        assert np.asarray(im).max() > 100  # some points drawn
    assert "frames/s" in capsys.readouterr().out


@pytest.mark.timeout(120)
@pytest.mark.parametrize("up", ["+y", "-z"])
def test_voxels_are_written_in_the_calibration_s_world(tmp_path, sequence, up):
    """A y-up (an OpenSim or Pose2Sim world) or z-down calibration's voxels (a board on the
    floor) come out in that world: the same voxels as the z-up calibration's, turned (and
    flipped), with the bounds, the voxel size and the up axis said in voxels.json; --bounds is
    read in that world too."""
    import shutil

    from common.calibration import load_calibration
    from common.world import AXIS_VECTORS, world_frame

    world = world_frame(up)
    turned = tmp_path / "turned"
    shutil.copytree(sequence, turned)
    save_calibration(world.studio_to_user(load_calibration(sequence / "calibration.json")), turned / "calibration.json")
    args = ["--grid", "16", "--pictures", "0", "--quiet"]
    assert main(["voxels", str(sequence), "--out", str(tmp_path / "z"), *args]) == 0
    assert main(["voxels", str(turned), "--out", str(tmp_path / "y"), *args]) == 0
    z, y = (load_voxels(tmp_path / name / "voxels" / "000001.npz") for name in ("z", "y"))
    centres = lambda points: sorted(map(tuple, np.round(points, 6)))
    assert y.occupied.any() and centres(y.centres(y.occupied)) == centres(world.points_to_user(z.centres(z.occupied)))
    summary = json.loads((tmp_path / "y" / "voxels.json").read_text())
    assert summary["world_up"] == up
    lo, hi = np.array(summary["bounds"])
    axis = int(np.abs(AXIS_VECTORS[up]).argmax())  # the box's height, from the floor along the up axis
    assert hi[axis] - lo[axis] == pytest.approx(2.2) and (lo[axis] if up[0] == "+" else hi[axis]) == pytest.approx(0.0)
    assert summary["voxel_size"] == pytest.approx(list(y.voxel_size))
    assert main(["voxels", str(turned), "--out", str(tmp_path / "given"), "--bounds", *map(str, [*lo, *hi]), *args]) == 0
    given = load_voxels(tmp_path / "given" / "voxels" / "000001.npz")
    assert given.occupied.sum() == y.occupied.sum()


def test_voxels_command_errors(tmp_path, sequence, capsys):
    assert main(["voxels", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert main(["voxels", str(sequence), "--out", str(tmp_path / "o"), "--grid", "1"]) == 2
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "calibration.json").write_text((sequence / "calibration.json").read_text())
    (bare / "images" / "cam1").mkdir(parents=True)
    write_sequence_meta(bare, [0], 30.0, [])
    assert main(["voxels", str(bare), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "silhouettes" in err and "grid" in err


def test_live_command_reports_stages(sequence, capsys):
    assert main(["live", str(sequence), "--grid", "32", "--repeat", "2", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 4
    assert [s["name"] for s in report["stages"]] == ["acquire", "voxels", "surface", "ellipsoids"]
    assert all(s["mean_ms"] > 0 for s in report["stages"])
    assert report["frames_per_second"] > 0 and report["latency_ms"]["max"] >= report["latency_ms"]["mean"]


def test_live_command_errors(tmp_path, sequence, capsys):
    assert main(["live", str(sequence), "--repeat", "0"]) == 2
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "calibration.json").write_text((sequence / "calibration.json").read_text())
    write_sequence_meta(bare, [0], 30.0, [])
    assert main(["live", str(bare)]) == 2
    assert "repeat" in capsys.readouterr().err


def test_silhouette_centre_ignores_cameras_that_see_only_noise():
    """A small ball at the studio's edge, out of two of eight views, with Cheung-like specks in
    every image: the two cameras that see only specks would pull the centre to their images'
    middle; their blobs are too small to count."""
    from common.voxels import silhouette_centre

    studio = circle_studio(8, 320, 240)
    centre = np.array([0.0, 2.1, 0.9])
    masks = render_ellipsoids(studio, [centre], [np.eye(3)], [[0.15] * 3])
    rng = np.random.default_rng(0)
    specks = rng.random(masks.shape) < 0.02  # single-pixel noise, 2% of the pixels
    blind = [k for k in range(len(studio)) if not masks[k].any()]
    assert len(blind) >= 1  # the ball is out of some views
    found = silhouette_centre(studio, masks | specks)
    assert np.linalg.norm(found - centre) < 0.1
    assert np.allclose(silhouette_centre(studio, masks), found, atol=0.05)


def test_the_default_box_holds_the_actor_wherever_the_take_puts_it(tmp_path, capsys):
    """``mocap voxels`` without --bounds: one box around the silhouettes' centres of the take's
    frames, not around the cameras' aim point, which a real rig's actor can sit beside (the
    seated recording: 0.5 m of the actor cut off)."""
    from common.voxels import bounds_around, default_bounds

    studio = circle_studio(8, 320, 240, radius=4.0)
    walk = [np.array([-1.5, 0.4, 0.9]), np.array([0.2, 0.5, 0.9]), np.array([1.6, 0.3, 0.9])]
    box = bounds_around(studio, [walk[0], None, *walk[1:]])
    for c in walk:  # each place with its 1.2 m margin either side, on the floor, 2.2 m high
        assert np.all(box[0] <= c - [1.2, 1.2, 0.9] + 0.13) and np.all(c + [1.2, 1.2, 0] <= box[1] + 0.13)
    assert box[0, 2] == 0.0 and box[1, 2] == pytest.approx(2.2)
    assert np.array_equal(bounds_around(studio, [None]), default_bounds(studio))

    root = tmp_path / "seq"
    save_calibration(studio, root / "calibration.json")
    frames = range(len(walk))
    for frame, c in zip(frames, walk):
        masks = render_ellipsoids(studio, [c], [np.eye(3)], [[0.25, 0.25, 0.8]])
        for cam, mask in zip(studio, masks):
            write_mask_png(root / "silhouettes" / cam.name / f"{frame:06d}.png", mask)
    write_sequence_meta(root, list(frames), 30.0, studio.names)
    out = tmp_path / "vox"
    assert main(["voxels", str(root), "--out", str(out), "--grid", "48", "--quiet"]) == 0
    summary = json.loads((out / "voxels.json").read_text())
    lo, hi = np.array(summary["bounds"])
    assert lo[0] < -2.6 and hi[0] > 2.7  # the whole walk, not the middle 2.4 m
    for frame, row in zip(frames, summary["frames"]):
        result = load_voxels(out / "voxels" / f"{frame:06d}.npz")
        occupied = result.occupied
        assert row["occupied"] > 100
        # nothing of the actor at the box's faces: it is inside
        assert not (occupied[0].any() or occupied[-1].any() or occupied[:, 0].any() or occupied[:, -1].any())


def test_a_grid_too_large_for_memory_is_refused(tmp_path, sequence, capsys):
    assert main(["voxels", str(sequence), "--out", str(tmp_path / "o"), "--grid", "1500"]) == 2
    err = capsys.readouterr().err
    assert "--grid" in err and "256" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
