"""`mocap bench init` (issue 7): which clips it runs on and how it reports them (server/benchmarks.py)."""
from __future__ import annotations

from pathlib import Path

import pytest

from server import benchmarks
from server.cli import main

BUNDLED = sorted((Path(__file__).resolve().parents[1] / "common" / "data" / "clips").glob("*.bvh"))


def _row(clip: str, start: str, frame: int, first: float) -> dict:
    return {"clip": clip, "start": start, "start_frame": frame, "frames": 3, "first_frame_error_mm": first,
            "first_frame_ok": first <= benchmarks.INIT_TARGET_MM, "first_frame_search_error_mm": first + 4.5,
            "first_frame_seconds": 7.5,
            "auto_mean_joint_error_mm": first - 2.0, "truth_start_mean_joint_error_mm": 20.0,
            "auto_minus_truth_start_mm": first - 22.0, "auto_last_frame_error_mm": 21.0,
            "truth_start_last_frame_error_mm": 20.0}


def test_shared_clips_lists_the_bvh_files_one_folder_down(tmp_path):
    assert benchmarks.shared_clips(tmp_path / "missing") == []
    for name in ("b/02_01.bvh", "a/01_01.bvh", "a/notes.txt", "top.bvh"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("")
    assert benchmarks.shared_clips(tmp_path) == [tmp_path / "a/01_01.bvh", tmp_path / "b/02_01.bvh"]


@pytest.fixture
def captured(monkeypatch):
    """Replaces init_rows; records the clips and options it was called with."""
    calls = []

    def fake(clips, frames, workdir, seed=0, tpose=False, options=None, first_frame_only=False, jobs=1):
        calls.append({"clips": list(clips), "frames": frames, "tpose": tpose, "search": options.refine_search,
                      "hops": options.refine_hops, "first_frame_only": first_frame_only, "jobs": jobs})
        return [_row(c.name, "start", 1, 30.0) for c in clips]

    monkeypatch.setattr(benchmarks, "init_rows", fake)
    return calls


def test_bench_init_defaults_to_the_shared_clips(tmp_path, monkeypatch, captured, capsys):
    shared = tmp_path / "mocap"
    (shared / "cmu").mkdir(parents=True)
    (shared / "cmu" / "05_02.bvh").write_text("")
    monkeypatch.setattr(benchmarks, "SHARED_CLIPS", shared)
    assert main(["bench", "init", "--frames", "2", "--tpose", "--json", str(tmp_path / "rows.json")]) == 0
    assert captured[-1] == {"clips": [shared / "cmu" / "05_02.bvh"], "frames": 2, "tpose": True, "search": False,
                            "hops": 0, "first_frame_only": False, "jobs": 1}
    assert (tmp_path / "rows.json").exists()
    assert "05_02.bvh" in capsys.readouterr().out
    assert main(["bench", "init", "--bundled", "--refine-search", "--refine-hops", "20"]) == 0
    assert captured[-1]["clips"] == BUNDLED and not captured[-1]["tpose"] and captured[-1]["search"]
    assert captured[-1]["hops"] == 20
    assert main(["bench", "init", "--bundled", "--frames", "100", "--first-frame-only", "--jobs", "2"]) == 0
    assert captured[-1]["first_frame_only"] and captured[-1]["frames"] == 100 and captured[-1]["jobs"] == 2


def test_bench_init_falls_back_to_the_bundled_clips(tmp_path, monkeypatch, captured):
    monkeypatch.setattr(benchmarks, "SHARED_CLIPS", tmp_path / "no-shared-data")
    assert main(["bench", "init", "--frames", "1"]) == 0
    assert captured[-1]["clips"] == BUNDLED and len(BUNDLED) >= 3


def test_bench_init_rejects_a_missing_clip(tmp_path, captured, capsys):
    assert main(["bench", "init", str(tmp_path / "nope.bvh")]) == 2
    assert "nope.bvh" in capsys.readouterr().err and not captured


def test_bench_init_rejects_negative_hops(captured, capsys):
    assert main(["bench", "init", "--bundled", "--refine-hops", "-1"]) == 2
    assert "--refine-hops: expected an integer >= 0" in capsys.readouterr().err and not captured


def test_init_table_counts_first_frames_on_target(capsys):
    rows = [_row("05_02.bvh", "start", 1, 31.0), _row("05_02.bvh", "random", 300, 80.0),
            _row("05_02.bvh", "tpose", 0, 12.0)]
    benchmarks.print_init_table(rows)
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 5 and "random" in out[2] and "80.0" in out[2]
    assert "search mm" in out[0] and "84.5" in out[2]  # the search's first frame, before the backward pass
    assert out[-1] == "first frame <= 50 mm: 2 of 3"


@pytest.mark.timeout(120)
def test_a_start_that_cannot_be_initialised_is_a_failed_row(tmp_path, monkeypatch, capsys):
    """No actor in the voxels (one out of most views) fails that run, not the benchmark."""
    from common.errors import UserError
    from server import session

    fitted = []

    def no_actor(model, seq, out_dir, options, solver, init=None, max_frames=None, **kw):
        fitted.append(max_frames)
        raise UserError("automatic initialisation failed on the first frame: need at least 8 surface voxels, got 0")

    monkeypatch.setattr(session, "run_fit", no_actor)
    rows = benchmarks.init_rows(BUNDLED[:1], 1, tmp_path)
    assert fitted == [None, None]
    benchmarks.init_rows(BUNDLED[:1], 2, tmp_path, first_frame_only=True)  # the first frame alone
    assert fitted[2:] == [1, 1]
    assert [(r["start"], r["first_frame_ok"]) for r in rows] == [("start", False), ("random", False)]
    assert all("surface voxels" in r["error"] for r in rows)
    benchmarks.print_init_table(rows)
    out = capsys.readouterr().out.splitlines()
    assert "failed: automatic initialisation" in out[1] and out[-1] == "first frame <= 50 mm: 0 of 2"


def test_search_error_is_the_forward_fit_of_a_refined_first_frame(model, small_loaded):
    import numpy as np

    seq, truth = small_loaded
    frame = seq.frames[0]
    true = truth[frame].params
    off = true.copy()
    off[0] += 0.05  # the whole body 50 mm aside
    refined = {"frame": frame, "params": true.tolist(), "first_pass": {"params": off.tolist(), "energy": 1}}
    assert np.isclose(benchmarks.search_error_mm(model, refined, truth), 50.0)
    assert np.isclose(benchmarks.search_error_mm(model, {"frame": frame, "params": true.tolist()}, truth), 0.0,
                      atol=1e-6)
