"""Units conversion and the ROS-free plant behind the simulator node."""

import math

import numpy as np
import pytest

from tsr_sim import dynamics
from tsr_sim.plant import Plant, PlantConfig, Rejection, Status
from tsr_sim.units import Scale


def test_paper_scale_in_si():
    scale = Scale(mass=20.0)
    # One step h = 0.01 tau is 8.47 s of orbit time (../shared/TSR_PHYSICS.md).
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


def make_plant(**kw):
    return Plant(PlantConfig(max_tension=50.0, **kw))


def test_plant_follows_the_dynamics_module():
    plant = make_plant(substeps=10)
    x = dynamics.PAPER_INITIAL_STATE.copy()
    tension = plant.config.scale.u_to_tension(2.0)
    for k in range(5):
        assert plant.submit(tension, step=k) is None
        x = dynamics.rk4_step(x, 2.0, 0.01, 10)
    np.testing.assert_allclose(plant.state, x, rtol=1e-12)
    assert plant.step_index == 5 and plant.accepted == 5


@pytest.mark.parametrize('tension, step, reason', [
    (math.nan, 0, Rejection.NON_FINITE), (math.inf, 0, Rejection.NON_FINITE),
    (-0.1, 0, Rejection.NEGATIVE), (50.1, 0, Rejection.OVER_LIMIT), (1.0, 3, Rejection.STALE)])
def test_bad_commands_never_reach_the_integrator(tension, step, reason):
    plant = make_plant()
    before = plant.state.copy()
    assert plant.submit(tension, step=step) is reason
    assert plant.counters[reason] == 1 and plant.accepted == 0
    np.testing.assert_array_equal(plant.state, before)
    assert plant.step_index == 0


def test_leaving_the_domain_halts_with_a_status_not_nans():
    # l = 0.01 reeling in at l' = -2 with no tension: the length crosses zero within a step.
    plant = make_plant(initial_state=[0.0, 0.0, -0.99, -2.0], substeps=1)
    plant.submit(0.0)
    assert plant.status is Status.HALTED_OUT_OF_DOMAIN
    assert 'left the model domain' in plant.message
    assert dynamics.in_domain(plant.state) and plant.step_index == 0
    plant.submit(0.0)   # ignored while halted
    assert plant.step_index == 0
    assert plant.reset(dynamics.PAPER_INITIAL_STATE) is None
    assert plant.status is Status.RUNNING


def test_reset_refuses_states_outside_the_domain():
    plant = make_plant()
    assert 'outside the model domain' in plant.reset([0.0, 0.0, -1.5, 0.0])
    assert 'needs 4 components' in plant.reset([0.0, 0.0])


def test_noise_is_seeded_and_sized():
    a = make_plant(sensor_noise_std=(0.01, 0, 0, 0), seed=7)
    b = make_plant(sensor_noise_std=(0.01, 0, 0, 0), seed=7)
    np.testing.assert_array_equal(a.measure(), b.measure())
    assert a.measure()[0] != 0.0 and a.measure()[1] == a.state[1]
    with pytest.raises(ValueError, match='sensor_noise_std needs 4'):
        make_plant(sensor_noise_std=(0.1,))


def test_finishes_after_max_steps():
    plant = make_plant(max_steps=3)
    for k in range(3):
        plant.submit(1.0, step=k)
    assert plant.status is Status.FINISHED and plant.step_index == 3
