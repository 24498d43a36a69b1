"""tools/actor_size_scan.py: the body thickened for its girth scan keeps its bones and its
longest radii, and fits the walk's first frame best at the model's own girth."""
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, load_tool


def test_thickened_keeps_the_bones_and_each_ellipsoids_longest_radius(model):
    thickened = load_tool("actor_size_scan").thickened
    thick = thickened(model, 1.3)
    np.testing.assert_array_equal(thick.joint_rest, model.joint_rest)
    rows, longest = np.arange(16), model.ellipsoid_radii.argmax(axis=1)
    np.testing.assert_array_equal(thick.ellipsoid_radii[rows, longest], model.ellipsoid_radii[rows, longest])
    others = np.ones(model.ellipsoid_radii.shape, bool)
    others[rows, longest] = False
    np.testing.assert_allclose(thick.ellipsoid_radii[others], 1.3 * model.ellipsoid_radii[others])
    assert thick.fingerprint != model.fingerprint
    np.testing.assert_array_equal(thickened(model, 1.0).ellipsoid_radii, model.ellipsoid_radii)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_walks_first_frame_fits_best_at_the_models_girth(small_sequence):
    out = subprocess.run([sys.executable, str(REPO / "tools" / "actor_size_scan.py"), str(small_sequence),
                          "--scales", "1.0", "--girths", "0.8,1.0,1.3"], capture_output=True, text=True, timeout=280)
    assert out.returncode == 0, out.stderr
    xor = {line.split("girth ")[1].split(":")[0]: int(line.split("XOR ")[1].split()[0])
           for line in out.stdout.splitlines() if "girth" in line}
    assert set(xor) == {"0.80", "1.00", "1.30"} and xor["1.00"] < min(xor["0.80"], xor["1.30"])
