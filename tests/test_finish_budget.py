"""tools/finish_budget.py: the finish again on a run fitted without it, per budget."""
from __future__ import annotations

import json

import pytest

from conftest import load_tool
from server.cli import main as mocap


@pytest.mark.timeout(300)
def test_the_finish_again_per_budget_on_a_run_without_it(small_sequence, tmp_path, capsys):
    """A run fitted with the finish turned off, finished again by the tool with one and two
    evolutions of two budgets: one line per setting, each saying how many frames came lower;
    the errors come from the poses (lower or equal energy is kept, so at most every frame);
    budgets that are not whole numbers >= 1 are refused."""
    assert mocap(["fit", str(small_sequence), "--out", str(tmp_path / "fit"), "--quiet", "--frames", "2",
                  "--set", "fit.schedules={finish_evolutions=0}"]) == 0
    summary = json.loads((tmp_path / "fit" / "summary.json").read_text())
    assert summary["frames_finished"] == 0 and summary["finish_seconds_per_frame"] < 0.01
    capsys.readouterr()
    tool = load_tool("finish_budget")
    assert tool.main([str(tmp_path / "fit"), str(small_sequence), "--evolutions", "1,2",
                      "--evaluations", "500,1000"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("as fitted: ") and len(out) == 5
    settings = [line.split(":")[0] for line in out[1:]]
    assert settings == [f"{n} evolution(s) of {e} evaluations" for n in (1, 2) for e in (500, 1000)]
    for line in out[1:]:
        lower = int(line.split("; ")[1].split(" of ")[0])
        assert 0 <= lower <= 2 and line.split("; ")[1].endswith("of 2 frames lower")
    with pytest.raises(SystemExit):
        tool.main([str(tmp_path / "fit"), str(small_sequence), "--evaluations", "0"])
