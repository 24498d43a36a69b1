"""tools/fit_diagnostics.py: energies against the truth's, lag, and a restart from the truth."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from server.cli import main as mocap

TOOL = Path(__file__).resolve().parents[1] / "tools" / "fit_diagnostics.py"


def load_tool():
    spec = importlib.util.spec_from_file_location("fit_diagnostics", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.timeout(300)
def test_diagnostics_compare_a_run_with_the_truth(small_sequence, tmp_path, capsys):
    from common.sequence import load_sequence

    assert mocap(["fit", str(small_sequence), "--out", str(tmp_path / "fit"), "--quiet"]) == 0
    frames = load_sequence(small_sequence).frames
    capsys.readouterr()
    assert load_tool().main([str(tmp_path / "fit"), str(small_sequence), "--every", "1",
                             "--restart-at", str(frames[1])]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[1] for line in out[:len(frames)]] == [str(f) for f in frames]
    assert out[len(frames)].startswith("the truth's energy is lower in ") and out[len(frames)].endswith(f"of {len(frames)} frames")
    assert out[len(frames) + 1].startswith("root error along its motion:")
    assert out[-1].startswith("last 20 frames:") and f"truth at frame {frames[1]}" in out[-1]


def test_a_restart_must_be_a_fitted_frame_after_the_first(small_sequence, tmp_path):
    from common.sequence import load_sequence

    assert mocap(["fit", str(small_sequence), "--out", str(tmp_path / "fit"), "--quiet", "--frames", "2"]) == 0
    first = load_sequence(small_sequence).frames[0]
    with pytest.raises(SystemExit, match="restart-at"):
        load_tool().main([str(tmp_path / "fit"), str(small_sequence), "--restart-at", str(first)])
