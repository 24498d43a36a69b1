"""tools/arm_twist_report.py: a frame's fits, the truth's basin and an arm's twists, each scored."""
from __future__ import annotations

import re

import pytest

from conftest import load_tool
from server.cli import main as mocap


@pytest.mark.timeout(300)
def test_the_report_scores_each_fit_against_the_truth(small_sequence, tmp_path, capsys):
    from common.sequence import load_sequence

    out = tmp_path / "fit"
    assert mocap(["fit", str(small_sequence), "--out", str(out), "--quiet", "--frames", "2"]) == 0
    frame = load_sequence(small_sequence).frames[1]
    capsys.readouterr()
    report = load_tool("arm_twist_report")
    assert report.main([str(out), str(small_sequence), "--frame", str(frame), "--arm", "left_arm"]) == 0
    lines = capsys.readouterr().out.splitlines()
    scored = [re.search(r"(\d+) pixels +([\d.]+) / +([\d.]+) mm$", line) for line in lines]
    assert all(scored), lines
    names = [line[:44].strip() for line in lines]
    assert names[0] == "the fit kept" and "the truth's basin (fitted from the truth)" in names
    assert sum(n.startswith("left_arm twist") for n in names) == 14  # seven twists, two bends
    basin = scored[names.index("the truth's basin (fitted from the truth)")]
    assert float(basin.group(2)) < 15.0  # the truth's own basin is near it
