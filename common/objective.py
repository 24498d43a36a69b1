"""The objective the optimizers minimise: an energy backend over a frame's windows
(``make_energy``: ``cpu`` analytic ellipsoids, ``gl`` rendered meshes, ``volume`` voxel
distances) plus the priors and completions the torso's solves add (``SpinePrior``,
``HeldLimbs``). Both optimizers (``common.optimize`` in Python, ``common.powell_cpu`` compiled)
take what this module builds; the energy modules import neither, so there is no import circle.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from common.body import P, BodyModel, clip_to_limits, hold_limbs_in_world
from common.conic_bits import pack_rows
from common.energy import CpuEnergy, EnergySetup, VolumeEnergy, Window

ENERGY_BACKENDS = {"cpu": CpuEnergy, "volume": VolumeEnergy}


def make_energy(backend: str, model: BodyModel, setup: EnergySetup):
    if backend == "gl":
        from common.energy_gl import GlEnergy

        return GlEnergy(model, setup)
    try:
        return ENERGY_BACKENDS[backend](model, setup)
    except KeyError:
        raise ValueError(f"unknown energy backend {backend!r}; expected cpu, gl or volume") from None


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the energies' compiled kernels now, by building and
    evaluating a tiny pre-rendered energy and a Powell solve on it: a client does this before it
    takes work, so that its first solve is not many seconds late (the server would hand that
    limb to another client)."""
    from common.body import load_body_model, rest_params
    from common.camera import circle_studio
    from common.powell_cpu import powell_cpu  # compiled against common.energy's kernels

    model = load_body_model()
    studio = circle_studio(1, 16, 16)
    masks = np.zeros((1, 16, 16), dtype=bool)
    setup = EnergySetup(studio, (Window(0, 0, 16, 16),), masks, (4,), rest_params(model))
    energy = CpuEnergy(model, setup)
    energy(rest_params(model))
    powell_cpu(energy, rest_params(model), [11], np.array([0.1]), 0.1, 1e-4, 10)
    # a solve's windows are cut from the frame's packed rows (conic_bits.window_value_bits)
    CpuEnergy(model, replace(setup, inputs=None, packed=pack_rows(masks)))


@dataclass(frozen=True)
class SpinePrior:
    """The torso energy plus a soft prior against twisting the spine: ``weight`` silhouette
    pixels per rad^2 of the chest's twist against the pelvis.

    A round pelvis and abdomen make the twist between pelvis and chest almost invisible in
    silhouettes: without a prior the pelvis heading drifts, traded against spine twist and
    hip rotations. The prior keeps that trade-off where the anatomy puts it.
    """

    energy: Callable
    weight: float

    def __post_init__(self):
        if not self.weight > 0:  # the compiled Powell adds the prior only for a positive weight
            raise ValueError(f"the spine twist prior's weight must be positive, got {self.weight}")

    def __call__(self, params: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(params)
        return self.energy(p) + self.weight * p[:, P["spine_z"]] ** 2


def with_spine_prior(energy, weight: float):
    """``energy`` with the spine twist prior of ``weight`` (itself where the weight is 0)."""
    return SpinePrior(energy, weight) if weight > 0 else energy


@dataclass(frozen=True)
class HeldLimbs:
    """The torso's candidates completed: the limbs held in the world orientation they have at
    the reference pose (``hold_limbs_in_world``), then clipped into the joint limits."""

    model: BodyModel
    reference_rotations: np.ndarray  # (16, 3, 3) the reference pose's segment rotations

    def __call__(self, candidates: np.ndarray) -> np.ndarray:
        """(B, 35) -> (B, 35)"""
        return clip_to_limits(hold_limbs_in_world(self.model, candidates, None, self.reference_rotations))
