"""tools/speed_against_version.py: this version timed beside an earlier one checked out in a
git worktree. Slow (both versions compile their kernels): `make test-slow`."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from speed_against_version import main  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900),
              pytest.mark.skipif(not (ROOT / ".git").exists(), reason="needs the git checkout")]


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout


def test_the_same_version_beside_itself_leaves_no_worktree_and_fits_alike_when_unchanged(tmp_path, capsys):
    worktrees = git("worktree", "list")
    seq = tmp_path / "walk"
    subprocess.run([sys.executable, "-m", "server.cli", "synth", "--out", str(seq), "--frames", "3", "--step", "4",
                    "--noise", "cheung", "--quiet"], cwd=ROOT, check=True)
    out = tmp_path / "speed.json"
    assert main(["HEAD", "--frames", "3", "--repeats", "1", "--sequence", str(seq), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    for version in ("earlier", "this"):
        row = result[version]
        assert len(row["runs_seconds_per_frame"]) == 1 and row["best_seconds_per_frame"] > 0
        assert row["mean_joint_error_mm"] > 0
    assert result["speedup"] > 0
    if not git("status", "--porcelain", "--untracked-files=no"):  # the working tree is HEAD: the same fit
        assert result["earlier"]["mean_joint_error_mm"] == result["this"]["mean_joint_error_mm"]
    assert git("worktree", "list") == worktrees
    assert main(["no-such-version", "--sequence", str(seq)]) == 2  # one error line, no traceback
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("speed_against_version: error: no-such-version")
