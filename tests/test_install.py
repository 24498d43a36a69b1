"""A clean install: the wheel builds without packaging warnings, installs in a fresh virtual
environment outside the repository, and ``mocap demo`` runs there on its bundled data; a
developer's editable install (``make venv``) warns of nothing either.

Slow (a venv with every dependency): ``make install-test``, which CI runs."""
from __future__ import annotations

import json
import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEMO_FRAMES = 3

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1200)]


def test_wheel_installs_outside_the_repo_and_runs_the_demo(tmp_path):
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-cache-dir", "-w",
                            str(tmp_path / "wheel"), str(ROOT)], capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr[-2000:]
    assert "Warning" not in build.stdout + build.stderr, (build.stdout + build.stderr)[-3000:]
    wheel = next((tmp_path / "wheel").glob("silhouette_mocap-*.whl"))
    env_dir = tmp_path / "env"
    venv.create(env_dir, with_pip=True)
    pip = subprocess.run([str(env_dir / "bin" / "pip"), "install", "--quiet", str(wheel)], capture_output=True,
                         text=True, timeout=900)
    assert pip.returncode == 0, pip.stderr[-2000:]
    work = tmp_path / "work"  # outside the repository: only the installed package can be found
    work.mkdir()
    demo = subprocess.run([str(env_dir / "bin" / "mocap"), "demo", "--frames", str(DEMO_FRAMES)], cwd=work,
                          capture_output=True, text=True, timeout=600)
    assert demo.returncode == 0, (demo.stdout + demo.stderr)[-3000:]
    result = work / "demo" / "result"
    assert len((result / "poses.jsonl").read_text().splitlines()) == DEMO_FRAMES
    assert json.loads((result / "summary.json").read_text())["frames"] == DEMO_FRAMES
    assert (result / "report.html").is_file() and (result / "motion.bvh").is_file()
    assert "mean joint error" in demo.stdout
    # the editable install `make venv` makes, into the same environment: no setuptools warning
    editable = subprocess.run([str(env_dir / "bin" / "pip"), "install", "--no-deps", "-e", str(ROOT)],
                              capture_output=True, text=True, timeout=600)
    assert editable.returncode == 0, editable.stderr[-2000:]
    assert "Warning" not in editable.stdout + editable.stderr, (editable.stdout + editable.stderr)[-3000:]
