"""tools/posture_report.py: a result's posture without truth (the real take's check)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

from common.body import P, forward_kinematics, joints_dict, load_body_model, rest_params  # noqa: E402
from common.world import world_frame  # noqa: E402
from posture_report import posture_figures  # noqa: E402

pytestmark = pytest.mark.timeout(120)


def records_of(scale: float, up: str, params: np.ndarray) -> list[dict]:
    """Records as a fit writes them: parameters in the fit frame, joints in the user's world."""
    model = load_body_model().scaled(scale)
    joints = world_frame(up).points_to_user(forward_kinematics(model, params).joints)
    return [{"params": p.tolist(), "joints": joints_dict(j), "world_up": up} for p, j in zip(params, joints)]


@pytest.mark.parametrize("up", ["+z", "-z"])
@pytest.mark.parametrize("scale", [1.0, 1.4])
def test_a_standing_body_has_straight_legs_and_its_soles_on_the_floor(up, scale):
    """The body model standing with its pelvis at its own height: legs straight, each foot's
    lowest point within 2 cm of the floor and its ankle joint 6-10 cm above it (the ankle stands
    above the sole), in the fit frame whichever way the user's world points; a body standing
    10 cm higher has its soles 10 cm higher; a still body does not jitter."""
    model = load_body_model().scaled(scale)
    standing = rest_params(model, position=(0.3, -0.2, model.joint_rest[0, 2]))
    lifted = standing.copy()
    lifted[P["root_z"]] += 0.1
    fig = posture_figures(records_of(scale, up, np.stack([standing, standing, lifted])), scale)
    for side in ("l", "r"):
        assert np.all(np.array(fig[f"{side}_hip_bend_deg"]) < 10) and np.all(np.array(fig[f"{side}_knee_bend_deg"]) < 10)
        soles, ankles = np.array(fig[f"{side}_foot_lowest_m"]), np.array(fig[f"{side}_ankle_height_m"])
        assert np.all(np.abs(soles[:2]) < 0.02 * scale), soles
        assert np.all((ankles[:2] - soles[:2] > 0.06 * scale) & (ankles[:2] - soles[:2] < 0.1 * scale))
        np.testing.assert_allclose(soles[2] - soles[0], 0.1, atol=1e-9)
    assert fig["jitter_mm"][0] == pytest.approx(0.0, abs=1e-6) and fig["jitter_mm"][1] == pytest.approx(100.0)


def test_without_the_actors_size_the_soles_are_not_reported():
    params = rest_params(load_body_model())[None]
    fig = posture_figures(records_of(1.0, "+z", params))
    assert "l_foot_lowest_m" not in fig and "l_ankle_height_m" in fig


def test_a_folder_without_a_result_is_one_error_line_and_exit_2(tmp_path, capsys):
    from posture_report import main

    assert main([str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("posture_report: error: ") and "poses.jsonl" in err[0]
