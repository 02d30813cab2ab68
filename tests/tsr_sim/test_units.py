"""SI <-> dimensionless conversion (tsr_sim.units)."""

import math

import numpy as np
import pytest

from tsr_sim.units import Scale


def test_paper_scale_in_si():
    scale = Scale(mass=20.0)
    # One step h = 0.01 tau is 8.47 s of orbit time (docs/physics.md).
    assert scale.tau_to_seconds(0.01) == pytest.approx(8.4717, abs=1e-3)
    # u = 3 holds the equilibrium: 3 m Omega^2 L.
    assert scale.u_to_tension(3.0) == pytest.approx(3 * 20.0 * 1.1804e-3 ** 2 * 1e5)
    si = scale.state_to_si(np.array([0.1, 0.5, -0.99, 0.5]))
    np.testing.assert_allclose(si, [0.1, 0.5 * 1.1804e-3, 1000.0, 0.5 * 1e5 * 1.1804e-3])


def test_state_round_trip_planar_and_3d():
    scale = Scale(orbit_rate=2e-3, tether_length=5e3, mass=3.0)
    x = np.random.default_rng(0).normal(size=(7, 6))
    np.testing.assert_allclose(scale.state_from_si(scale.state_to_si(x)), x, atol=1e-12)
    np.testing.assert_allclose(scale.state_to_si(x)[:, 5], x[:, 5] * 2e-3)
    np.testing.assert_allclose(scale.state_from_si(scale.state_to_si(x[:, :4])), x[:, :4])


@pytest.mark.parametrize('bad', [0.0, -1.0, math.nan, math.inf])
def test_scale_rejects_bad_values(bad):
    with pytest.raises(ValueError, match='mass must be a finite number > 0'):
        Scale(mass=bad)
