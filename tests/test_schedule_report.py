"""tools/schedule_report.py: where a fit's evaluations go, and which proposer's start each
schedule keeps, counted on a real run without changing its poses."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import common.search as search  # noqa: E402
from schedule_report import Watcher  # noqa: E402
from schedule_report import main as schedule_report  # noqa: E402
from server.cli import main as mocap  # noqa: E402

pytestmark = pytest.mark.timeout(300)


@pytest.fixture
def saved_search():
    """What the tool wraps, to check that it puts everything back."""
    import server.session as session

    return search._fit_or_recall, search.run_schedule, session.run_schedule, dict(search.PROPOSERS)


def assert_restored(saved) -> None:
    import server.session as session

    assert (search._fit_or_recall, search.run_schedule, session.run_schedule, dict(search.PROPOSERS)) == saved


def params(out: Path) -> list:
    return [json.loads(line)["params"] for line in (out / "poses.jsonl").read_text().splitlines()]


def test_every_tracked_and_refined_frame_is_counted_once(small_sequence, tmp_path, saved_search, monkeypatch):
    """3 frames, the first from the truth's pose: each tracked once (TRACKING); the backward pass
    refines its first frame (2) by REFINE_SEARCH with hops, frames 1 and 0 by REFINE, frame 1
    (taken for poor) forwards and backwards once more from its neighbours' fits with hops, and
    frame 1 once more by REFINE where it stands out of its neighbours; the fits and re-detection's
    grids spend evaluations; the poses are those of the same fit unwatched."""
    import server.session as session

    standing_out = []  # each run's frames that stood out after the passes
    found = session.standing_out
    monkeypatch.setattr(session, "standing_out", lambda energies, ratio: standing_out.append(found(energies, ratio))
                        or standing_out[-1])
    poor = []  # the shares each run judged; frame 1 taken for poor, alone (no margin), in both runs
    monkeypatch.setattr(session, "poor_windows", lambda shares, ratio: poor.append(shares) or [(1, 1)])
    watcher = Watcher()
    watcher.install()
    try:
        assert mocap(["fit", str(small_sequence), "--out", str(tmp_path / "watched"), "--threads", "2", "--quiet"]) == 0
    finally:
        watcher.uninstall()
    assert_restored(saved_search)
    assert mocap(["fit", str(small_sequence), "--out", str(tmp_path / "plain"), "--threads", "1", "--quiet"]) == 0
    assert params(tmp_path / "watched") == params(tmp_path / "plain")
    report = watcher.report()
    assert sum(report["winners"]["TRACKING"].values()) == 3
    assert standing_out[0] in ([], [1]) and standing_out[1] == standing_out[0]
    assert len(poor) == 2 and len(poor[0]) == 3 and all(share > 0 for share in poor[0])
    # the window's frame forwards from frame 0's fit and backwards from frame 2's, by REFINE
    # with the window's hops
    assert sum(report["winners"]["REFINE"].values()) == 2 + len(standing_out[0])
    assert sum(report["winners"]["REFINE+AFTER_HOPS"].values()) == 2
    assert sum(report["winners"]["REFINE_SEARCH+AFTER_HOPS"].values()) == 1
    summary = json.loads((tmp_path / "plain" / "summary.json").read_text())
    assert summary["frames_poor_refined"] in (0, 1)
    tracking = [r for r in report["stages"] if r["schedule"] == "TRACKING"]
    assert tracking[0]["proposers"].startswith("start+start_turns") and tracking[0]["starts"] >= 3 * 5
    assert all(r["evaluations"] > 0 for r in report["stages"] if r["starts"])
    assert report["proposers_spending"]["redetected"]["evaluations"] > 0


def test_the_command_prints_and_writes_the_counts(small_sequence, tmp_path, saved_search, capsys):
    out = tmp_path / "report.json"
    assert schedule_report([str(small_sequence), "--threads", "1", "--refine-passes", "0", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "3 frames in" in printed and "joint error" in printed and "TRACKING" in printed
    report = json.loads(out.read_text())
    assert "REFINE" not in report["winners"] and report["fit"]["frames"] == 3
    assert_restored(saved_search)
