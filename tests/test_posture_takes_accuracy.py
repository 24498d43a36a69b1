"""tools/posture_takes_accuracy.py: synthesises and fits the real-like studio's posture takes,
started automatically, and reports each take's error against the truth."""
import json
import subprocess
import sys

import pytest

from conftest import REPO

TOOL = REPO / "tools" / "posture_takes_accuracy.py"


@pytest.mark.timeout(60)
def test_an_unknown_take_is_one_line_and_exit_2(tmp_path):
    out = subprocess.run([sys.executable, str(TOOL), "--takes", "seated,standing-chair", "--work", str(tmp_path)],
                         capture_output=True, text=True, timeout=50)
    assert out.returncode == 2
    assert out.stderr.strip() == ("posture_takes_accuracy: error: --takes: unknown standing-chair "
                                  "(see posture_takes_accuracy --help)")
    assert not list(tmp_path.iterdir())  # refused before anything is synthesised
    for bad in (["--jobs", "0"], ["--frames", "0"], ["--takes", ","], ["--work", str(TOOL)]):
        out = subprocess.run([sys.executable, str(TOOL), *bad], capture_output=True, text=True, timeout=50)
        assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, (bad, out.stderr)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_lying_take_is_found_from_the_automatic_start(tmp_path):
    out = subprocess.run([sys.executable, str(TOOL), "--takes", "lying_front", "--frames", "3", "--jobs", "1",
                          "--work", str(tmp_path), "--json", str(tmp_path / "rows.json")],
                         capture_output=True, text=True, timeout=280)
    assert out.returncode == 0, out.stderr[-2000:]
    (row,) = json.loads((tmp_path / "rows.json").read_text())
    assert row["take"] == "lying_front" and row["frames"] == 3 and row["static_props_m3"] == 0.0
    assert row["first_frame_max_error_mm"] < 50.0 and row["mean_joint_error_mm"] < 15.0
    assert "lying_front" in out.stdout and "mean: none" in out.stdout
