"""Shared fixtures: the body model, a small synthetic sequence, paths to the bundled clips.

The small sequence is 4 cameras at 160x120 (no overhead camera), 3 frames of the bundled CMU
walk, no noise, seed 0: cheap enough for every test file that needs real silhouettes.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
CLIPS_DIR = REPO / "common" / "data" / "clips"
BUNDLED_CLIPS = tuple(sorted(CLIPS_DIR.glob("*.bvh")))
WALK_CLIP = CLIPS_DIR / "cmu_12_01_walk.bvh"
SHARED_MOCAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"
SHARED_CLIPS = tuple(sorted(SHARED_MOCAP.glob("**/*.bvh"))) if SHARED_MOCAP.is_dir() else ()

SMALL_CAMERAS = 4
SMALL_SIZE = (160, 120)  # width, height
SMALL_FRAMES = 3


def load_tool(name: str):
    """The module of ``tools/NAME.py`` (the tools are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def model():
    from common.body import load_body_model

    return load_body_model()


@pytest.fixture(scope="session")
def small_studio():
    from common.camera import circle_studio

    return circle_studio(SMALL_CAMERAS, *SMALL_SIZE)


@pytest.fixture(scope="session")
def small_sequence(tmp_path_factory, model, small_studio) -> Path:
    """A read-only sequence folder: 4 cameras, 160x120, 3 frames, truth.jsonl. Copy before editing."""
    from common.synth import SynthOptions, synthesize

    out = tmp_path_factory.mktemp("small_sequence") / "seq"
    synthesize(model, small_studio, WALK_CLIP, out,
               SynthOptions(frames=SMALL_FRAMES, start=1, step=4, noise="none", surface="skinned", seed=0))
    return out


@pytest.fixture(scope="session")
def small_loaded(small_sequence):
    """(Sequence, truth dict) of the small sequence."""
    from common.sequence import load_sequence

    seq = load_sequence(small_sequence)
    return seq, seq.truth()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
