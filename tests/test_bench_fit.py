"""mocap bench fit / accuracy rows: their schema, and tracking scored apart from refinement."""
import json
import tempfile

import pytest

from common.fitting import FitOptions


@pytest.mark.timeout(300)
def test_fit_rows_time_tracking_and_the_refinement_from_one_run(tmp_path, monkeypatch):
    from server import benchmarks
    from server.commands.bench import bench_sequence

    scratch = tmp_path / "scratch"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    rows = benchmarks.fit_rows(bench_sequence(2, tmp_path / "seq"), frames=2)
    assert not list(scratch.iterdir())  # each run's result folder is removed
    by_mode = {r["mode"]: r for r in rows}
    assert list(by_mode) == ["single_xorpr", "single_xorpr_refined", "single_xor", "single_xorpr_no_turn_hypotheses",
                             "single_xorpr_no_polish"]
    for r in rows:
        assert set(r) >= {"mode", "energy_backend", "seconds_per_frame", "paper_seconds_per_frame"}
        assert r["seconds_per_frame"] > 0 and r["frames"] == 2
    assert by_mode["single_xorpr"]["paper_seconds_per_frame"] == benchmarks.PAPER_TABLE2["single_xorpr"]
    assert by_mode["single_xorpr_refined"]["seconds_per_frame"] > by_mode["single_xorpr"]["seconds_per_frame"]


@pytest.mark.timeout(300)
def test_accuracy_rows_score_the_result_and_tracking_alone(tmp_path):
    from server import benchmarks

    options = FitOptions(max_iterations=1, turn_hypotheses=0, refine_passes=1)
    (row,) = benchmarks.accuracy_rows(3, tmp_path, clips=("cmu_12_01_walk.bvh",), options=options)
    assert row["frames"] == 3 and row["refine_passes"] == 1
    for prefix in ("", "tracking_"):
        assert 0 < row[f"{prefix}mean_joint_error_mm"] <= row[f"{prefix}max_joint_error_mm"] < 100
        assert row[f"{prefix}first20_mean_mm"] == pytest.approx(row[f"{prefix}mean_joint_error_mm"])  # 3 frames
        over = row[f"{prefix}frames_over_max_target"]
        assert 0 <= over <= 3 and (over > 0) == (row[f"{prefix}max_joint_error_mm"] > 40.0)
    assert row["refine_seconds_per_frame"] > 0
    assert "drift_mm" not in row  # too few frames for a restart apart from the first 20


@pytest.mark.timeout(300)
def test_the_restart_tracks_the_last_frames_from_the_truth_of_the_first_of_them(model, small_loaded, tmp_path):
    """restarted_tail_errors_mm: the last frames in a run of their own, started at the truth of
    the first of them (which it keeps, as a run started from the truth does; so do the first 20
    frames that the last 20 are compared with), tracked with the options' tracking and no
    refinement."""
    from server import benchmarks
    from server.results import load_records

    seq, truth = small_loaded
    options = FitOptions(max_iterations=1, turn_hypotheses=0, refine_passes=1, refine_hops=2)
    errors = benchmarks.restarted_tail_errors_mm(model, seq, tmp_path / "tail", options, frames=2)
    assert errors.shape == (2,) and errors[0] == 0.0 and 0 < errors[1] < 60.0
    records = load_records(tmp_path / "tail")
    assert [r["frame"] for r in records] == seq.frames[-2:]
    summary = json.loads((tmp_path / "tail" / "summary.json").read_text())
    assert summary["refine_seconds_per_frame"] == 0 and summary["options"]["refine_passes"] == 0
