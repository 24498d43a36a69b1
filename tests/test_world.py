"""The world's up axis (common.world), the postures (common.postures) and multi-view mask
consistency (common.consistency)."""
import numpy as np
import pytest

from common.body import JOINT_NAMES, P, forward_kinematics, load_body_model, rigid_vertices
from common.camera import Studio, circle_studio
from common.consistency import supported_masks
from common.errors import UserError
from common.postures import POSTURES, posture_params, varied_posture
from common.world import UP_CHOICES, cameras_below_floor, detect_up, resolve_world, world_frame


def user_studio(studio: Studio, up: str) -> Studio:
    """Our z-up studio re-expressed in a world whose up axis is ``up``."""
    return world_frame(up).studio_to_user(studio)


@pytest.mark.parametrize("up", [u for u in UP_CHOICES if u != "auto"])
def test_detect_up_finds_each_axis_and_the_fit_frame_is_ours(up):
    ours = circle_studio(8, 320, 240)
    theirs = user_studio(ours, up)
    assert detect_up(theirs) == up
    world = resolve_world(theirs)
    back = world.studio_to_fit(theirs)
    point = np.array([[0.3, -0.2, 1.1]])
    for a, b in zip(ours, back):
        np.testing.assert_allclose(a.project(point), b.project(point), atol=1e-9)
    # studio_to_user and studio_to_fit undo each other
    for a, b in zip(theirs, world.studio_to_user(back)):
        np.testing.assert_allclose(b.R, a.R, atol=1e-12)
        np.testing.assert_array_equal(b.t, a.t)
    # points go to the user's frame and back; the user's frame projects with the user's cameras
    user_point = world.points_to_user(point)
    np.testing.assert_allclose(world.points_to_fit(user_point), point, atol=1e-12)
    np.testing.assert_allclose(theirs[0].project(user_point), ours[0].project(point), atol=1e-9)
    assert cameras_below_floor(theirs, world) == []


def test_cameras_below_the_floor_are_named_for_a_wrong_axis():
    studio = user_studio(circle_studio(4, 320, 240), "-z")
    assert cameras_below_floor(studio, world_frame("+z")) == [c.name for c in studio]
    with pytest.raises(UserError, match="--up"):
        world_frame("up")


def test_a_sequence_loaded_with_a_wrong_up_axis_says_so(small_sequence, capsys):
    """``mocap fit --up -z`` (or voxels, live, server) on a z-up rig: the cameras stand below the
    floor, as ``calib show`` warns; the fit would come out upside down without a word."""
    from common.sequence import load_sequence

    load_sequence(small_sequence, up="auto")
    assert capsys.readouterr().err == ""
    load_sequence(small_sequence, up="-z")
    err = capsys.readouterr().err
    assert err.count("warning:") == 1 and "below the floor (z = 0)" in err and "auto finds +z" in err
    load_sequence(small_sequence, up="-y")  # the floor of a y-up world is y = 0
    assert "below the floor (y = 0)" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(POSTURES))
def test_postures_stand_on_the_floor(name):
    model = load_body_model()
    params = posture_params(model, name, 0.4, -0.2, 1.0)
    lowest = rigid_vertices(model, forward_kinematics(model, params))[:, 2].min()
    assert abs(lowest) < 1e-9
    assert params[P["root_x"]] == 0.4 and params[P["root_heading"]] == 1.0


def test_seated_posture_bends_hips_and_knees_and_variation_is_seeded():
    model = load_body_model()
    seated = posture_params(model, "seated")
    joints = dict(zip(JOINT_NAMES, forward_kinematics(model, seated).joints[0]))
    assert 0.35 < joints["pelvis"][2] < 0.6          # on a chair's seat
    assert abs(joints["l_knee"][2] - joints["l_hip"][2]) < 0.1  # the thigh level
    a = varied_posture(model, "seated", np.random.default_rng(3))
    b = varied_posture(model, "seated", np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, seated)


def test_blobs_one_camera_sees_alone_are_dropped_and_the_actor_kept():
    from common.energy import EnergySetup, Window
    from common.objective import make_energy
    model = load_body_model()
    studio = circle_studio(6, 160, 120)
    params = posture_params(model, "seated")
    setup = EnergySetup(studio, tuple(Window(0, 0, 160, 120) for _ in studio), np.zeros((6, 120, 160), bool),
                        tuple(range(16)), params, prerender=False)
    masks = make_energy("cpu", model, setup).render(params)
    noisy = masks.copy()
    noisy[0, 2:10, 2:12] = True      # a light in one view
    noisy[3, 100:118, 140:158] = True  # a floor seam in another
    cleaned, removed = supported_masks(studio, noisy, np.array([0.0, 0.0, 0.6]))
    assert not cleaned[0, 2:10, 2:12].any() and not cleaned[3, 100:118, 140:158].any()
    np.testing.assert_array_equal(cleaned, masks)
    assert removed[0] == 80 and removed[3] == 18 * 18 and removed[1] == 0


@pytest.mark.parametrize("posture", ["rest", "seated"])
def test_a_streak_joined_to_the_actor_in_one_view_is_cut_off_and_the_actor_kept(posture):
    """A floor seam or shadow touching the actor's blob is one blob with it: kept as a blob, its
    pixels whose rays no other camera supports go; every pixel of the body stays, thin forearms
    that the coarse hull misses included."""
    from common.body import rest_params
    from common.energy import EnergySetup, Window
    from common.objective import make_energy
    model = load_body_model()
    studio = circle_studio(6, 160, 120)
    params = rest_params(model) if posture == "rest" else posture_params(model, "seated")
    setup = EnergySetup(studio, tuple(Window(0, 0, 160, 120) for _ in studio), np.zeros((6, 120, 160), bool),
                        tuple(range(16)), params, prerender=False)
    masks = make_energy("cpu", model, setup).render(params)
    rows, cols = np.nonzero(masks[2])
    bottom = rows.max()
    left = cols[rows == bottom].min()
    noisy = masks.copy()
    noisy[2, bottom - 2:bottom + 1, :left + 1] = True  # a streak along the floor out to the image's edge
    cleaned, removed = supported_masks(studio, noisy, np.array([0.0, 0.0, 0.6]))
    assert not np.any(masks & ~cleaned)                      # the actor whole, in every view
    assert not cleaned[2, bottom - 2:bottom + 1, :left - 30].any()  # the streak's far part gone
    assert removed[2] > 3 * (left - 30) and not removed[[0, 1, 3, 4, 5]].any()


def test_a_sequence_cleans_its_masks_unless_asked_not_to(small_sequence):
    from common.sequence import load_sequence

    cleaned, raw = load_sequence(small_sequence), load_sequence(small_sequence, clean_masks=False)
    frame = cleaned.frames[0]
    np.testing.assert_array_equal(raw.silhouettes(frame), raw.raw_silhouettes(frame))
    masks, removed = cleaned.cleaned(frame)
    np.testing.assert_array_equal(cleaned.silhouettes(frame), masks)
    assert not np.any(masks & ~raw.silhouettes(frame))  # cleaning only removes
    np.testing.assert_array_equal(removed, (raw.silhouettes(frame) & ~masks).sum(axis=(1, 2)))


def test_a_fitted_motion_in_a_z_down_world_is_drawn_z_up(model):
    from common.body import rest_params
    from common.export import FittedMotion

    params = rest_params(model)[None]
    fit = forward_kinematics(model, params).joints
    user = world_frame("-z").points_to_user(fit)
    records = [{"frame": 0, "params": params[0].tolist(), "world_up": "-z",
                "joints": {n: user[0, i].tolist() for i, n in enumerate(JOINT_NAMES)}}]
    motion = FittedMotion.from_records(records, 30.0)
    assert motion.up == "-z" and motion.joints[0, -1, 2] < 0  # the file's frame: the head at negative z
    np.testing.assert_allclose(motion.fit_joints, fit, atol=1e-12)


def _fake_size_search(monkeypatch, model, energies: dict, seen: list):
    """``choose_actor_scale`` with its fits replaced: 100 at the model's size, ``energies[size]``
    at another; each size fitted is appended to ``seen``. Returns a one-frame sequence."""
    from common.fitting import FrameResult
    from server import session

    monkeypatch.setattr(session, "frame_data", lambda *_: None)
    monkeypatch.setattr(session, "voxel_starts", lambda *_: [])
    monkeypatch.setattr(session, "run_schedule", lambda ctx, schedule, memo: FrameResult(np.zeros(35), 100.0, 1, 1))

    def fake_fit(actor, data, start, options, dispatch):
        seen.append(round(actor.height / model.height, 2))
        return FrameResult(start, energies[seen[-1]], 1, 1)

    monkeypatch.setattr(session, "fit_rounds", fake_fit)
    monkeypatch.setattr(session, "size_score", lambda data, fit, larger: fit.energy)
    return type("Seq", (), {"frames": [0]})()


@pytest.mark.parametrize("energies,chosen", [
    ({0.9: 99.0, 1.1: 97.0, 1.2: 96.0, 1.3: 98.0, 1.4: 99.0}, 1.0),  # a few per cent either way: the model's size
    ({0.9: 120.0, 1.1: 90.0, 1.2: 80.0, 1.3: 72.0, 1.4: 75.0}, 1.3),  # much less energy at 1.3: the actor is larger
    ({0.9: 120.0, 1.1: 90.0, 1.2: 80.0, 1.3: 72.0, 1.4: 66.0}, 1.4),  # a calibration 40% off (the seated take)
    ({0.9: 80.0, 1.1: 110.0, 1.2: 130.0, 1.3: 150.0, 1.4: 170.0}, 0.9),
])
def test_the_actor_size_changes_only_for_a_clear_gain(monkeypatch, model, energies, chosen):
    from common.fitting import FitOptions
    from server import session

    seq = _fake_size_search(monkeypatch, model, energies, [])
    assert session.choose_actor_scale(model, seq, FitOptions()).scale == chosen


@pytest.mark.parametrize("energies,fitted", [
    ({0.9: 104.0, 1.1: 103.0}, {0.9, 1.1}),  # higher on both sides: two sizes fitted
    ({0.9: 104.0, 1.1: 97.0, 1.2: 96.0, 1.3: 98.0}, {0.9, 1.1, 1.2, 1.3}),
    ({0.9: 120.0, 1.1: 90.0, 1.2: 80.0, 1.3: 72.0, 1.4: 66.0}, {0.9, 1.1, 1.2, 1.3, 1.4}),
])
def test_sizes_are_fitted_outward_while_the_energy_falls(monkeypatch, model, energies, fitted):
    from common.fitting import FitOptions
    from server import session

    seen = []
    seq = _fake_size_search(monkeypatch, model, energies, seen)
    for threads in (1, 2):
        seen.clear()
        session.choose_actor_scale(model, seq, FitOptions(), threads)
        assert set(seen) == fitted and len(seen) == len(fitted)


def test_a_chair_sat_on_does_not_make_the_actor_larger(tmp_path, model, monkeypatch):
    """A seated body on a chair, the model's own size: a larger body covers more of the chair
    while staying inside the silhouettes, so the plain XOR chose 1.1 (6.5% less); the size
    score, which counts model pixels outside the silhouettes twice, keeps 1.0."""
    from common.camera import circle_studio
    from common.fitting import FitOptions
    from common.sequence import load_sequence
    from common import scoring
    from common.synth import SynthOptions, synthesize
    from server import session

    synthesize(model, circle_studio(8, 320, 240), None, tmp_path / "seq",
               SynthOptions(frames=1, posture="seated", prop="chair"))
    seq = load_sequence(tmp_path / "seq")
    assert session.choose_actor_scale(model, seq, FitOptions(), threads=2).scale == 1.0
    monkeypatch.setattr(scoring, "SIZE_OUTSIDE_WEIGHT", 1.0)  # the plain XOR
    assert session.choose_actor_scale(model, seq, FitOptions(), threads=2).scale == 1.1


def test_a_crouch_is_not_taken_for_a_smaller_actor(tmp_path, model, monkeypatch):
    """A crouch of the model's own size: the thigh and calf ellipsoids poke out of the folded
    legs, less so at a smaller size, so a score that counts model pixels outside the
    silhouettes twice chose 0.9 (every frame 56-75 mm off); a smaller size is scored by the plain
    XOR, and 1.0 is kept."""
    from common.camera import circle_studio
    from common.fitting import FitOptions
    from common.sequence import load_sequence
    from common.synth import SynthOptions, synthesize
    from server import session

    synthesize(model, circle_studio(8, 320, 240), None, tmp_path / "seq", SynthOptions(frames=1, posture="crouching"))
    seq = load_sequence(tmp_path / "seq")
    assert session.choose_actor_scale(model, seq, FitOptions(), threads=2).scale == 1.0
    weighted = session.size_score
    monkeypatch.setattr(session, "size_score", lambda data, fit, larger: weighted(data, fit, True))  # both sides
    assert session.choose_actor_scale(model, seq, FitOptions(), threads=2).scale == 0.9


@pytest.mark.parametrize("posture", ["crouching", "seated", "lying_side"])
def test_posture_starts_face_the_way_the_actor_does(tmp_path, model, posture):
    """The best posture start of a crouch, a seat or a side-lying body stands where the actor is
    and faces its way (placed as they are, a crouch looked alike facing back)."""
    from common import voxels
    from common.camera import circle_studio
    from common.sequence import load_sequence
    from common.synth import SynthOptions, synthesize
    from common.proposals import posture_starts
    from server.session import frame_data

    synthesize(model, circle_studio(6, 160, 120), None, tmp_path / "seq",
               SynthOptions(frames=1, posture=posture, noise="none", seed=1))
    seq = load_sequence(tmp_path / "seq")
    truth = seq.truth()[seq.frames[0]].params
    data = frame_data(model, seq, seq.frames[0])
    best = posture_starts(model, data, voxels.silhouette_centre(data.studio, data.masks), 0.0)[0]
    turn = np.angle(np.exp(1j * (best[P["root_heading"]] - truth[P["root_heading"]])))
    assert abs(turn) < 0.5 and np.linalg.norm(best[:2] - truth[:2]) < 0.2
