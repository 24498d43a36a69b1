"""tools/fit_diagnostics.py: energies against the truth's, lag, and a restart from the truth."""
from __future__ import annotations

import pytest

from conftest import load_tool
from server.cli import main as mocap


@pytest.mark.timeout(300)
def test_diagnostics_compare_a_run_with_the_truth(small_sequence, tmp_path, capsys):
    from common.sequence import load_sequence

    assert mocap(["fit", str(small_sequence), "--out", str(tmp_path / "fit"), "--quiet"]) == 0
    frames = load_sequence(small_sequence).frames
    capsys.readouterr()
    assert load_tool("fit_diagnostics").main([str(tmp_path / "fit"), str(small_sequence), "--every", "1",
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
        load_tool("fit_diagnostics").main([str(tmp_path / "fit"), str(small_sequence), "--restart-at", str(first)])


@pytest.mark.timeout(300)
def test_chains_put_one_at_a_time_at_the_truth(small_sequence, tmp_path, capsys):
    """--chains: a frame fitted from the truth stays near it, and one line per frame gives the
    energy change of each of the six chains put at the truth alone; a second the fewest chains
    that lower it together, the straight line's highest energy, and the fit from halfway
    between the frame's neighbours; a frame not fitted is refused."""
    from common.body import CHAINS
    from common.sequence import load_sequence
    from server.results import load_records

    assert mocap(["fit", str(small_sequence), "--out", str(tmp_path / "fit"), "--quiet", "--frames", "3"]) == 0
    frames = load_sequence(small_sequence).frames
    capsys.readouterr()
    diagnostics = load_tool("fit_diagnostics")
    assert diagnostics.main([str(tmp_path / "fit"), str(small_sequence), "--chains", f"{frames[1]}"]) == 0
    out = capsys.readouterr().out.splitlines()
    (line,) = [x for x in out if "one chain at the truth" in x]
    (more,) = [x for x in out if "fewest chains" in x]
    assert more.split()[1] == str(frames[1])
    fewest = more.split("lower it: ")[1].split("  ")[0]
    assert fewest == "none" or all(n in CHAINS for n in fewest.split()[0].split("+"))
    assert int(more.split("highest ")[1].split()[0]) >= 0  # the fit's own energy is on the line
    assert f"halfway between frames {frames[0]} and {frames[2]}: " in more
    assert line.split()[1] == str(frames[1])
    from_truth_mm = float(line.split("fitted from the truth")[1].split("(")[1].split(" mm")[0])
    assert from_truth_mm < 15.0
    swaps = line.split("one chain at the truth: ")[1].split(", ")
    assert [s.split()[0] for s in swaps] == list(CHAINS)
    record = [r for r in load_records(tmp_path / "fit") if r["frame"] == frames[1]][0]
    assert int(line.split()[3]) == record["energy"]
    assert all(s.split()[1][0] in "+-" for s in swaps)  # changes, signed
    with pytest.raises(SystemExit, match="--chains"):
        load_tool("fit_diagnostics").main([str(tmp_path / "fit"), str(small_sequence), "--chains",
                                           f"{frames[-1] + 1000}"])
