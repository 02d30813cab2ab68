"""The simulated plant, ROS-free: command checks, domain halt, noise (tsr_sim.plant)."""

import math

import numpy as np
import pytest

from tsr_sim import dynamics
from tsr_sim.plant import Plant, PlantConfig, Rejection, Status


def make_plant(**kw):
    return Plant(PlantConfig(max_tension=50.0, **kw))


def submit(plant, tension, step=None):
    """What the simulator node does with a command: check it, then advance if accepted."""
    rejection = plant.accept(tension, step)
    if rejection is None:
        plant.advance(tension)
    return rejection


def test_plant_follows_the_dynamics_module():
    plant = make_plant(substeps=10)
    x = dynamics.PAPER_INITIAL_STATE.copy()
    tension = plant.config.scale.u_to_tension(2.0)
    for k in range(5):
        assert submit(plant, tension, step=k) is None
        x = dynamics.rk4_step(x, 2.0, 0.01, 10)
    np.testing.assert_allclose(plant.state, x, rtol=1e-12)
    assert plant.step_index == 5 and plant.accepted == 5


@pytest.mark.parametrize('tension, step, reason', [
    (math.nan, 0, Rejection.NON_FINITE), (math.inf, 0, Rejection.NON_FINITE),
    (-0.1, 0, Rejection.NEGATIVE), (50.1, 0, Rejection.OVER_LIMIT), (1.0, 3, Rejection.STALE)])
def test_bad_commands_never_reach_the_integrator(tension, step, reason):
    plant = make_plant()
    before = plant.state.copy()
    assert submit(plant, tension, step=step) is reason
    assert plant.counters[reason] == 1 and plant.accepted == 0
    np.testing.assert_array_equal(plant.state, before)
    assert plant.step_index == 0


def test_leaving_the_domain_halts_with_a_status_not_nans():
    # l = 0.01 reeling in at l' = -2 with no tension: the length crosses zero within a step.
    plant = make_plant(initial_state=[0.0, 0.0, -0.99, -2.0], substeps=1)
    submit(plant, 0.0)
    assert plant.status is Status.HALTED_OUT_OF_DOMAIN
    assert 'left the model domain' in plant.message
    assert dynamics.in_domain(plant.state) and plant.step_index == 0
    submit(plant, 0.0)   # ignored while halted
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
        submit(plant, 1.0, step=k)
    assert plant.status is Status.FINISHED and plant.step_index == 3


def test_an_initial_state_outside_the_domain_is_refused_at_construction():
    with pytest.raises(ValueError, match=r'initial_state \[0.0, 0.0, -1.5, 0.5\]: reset state is '
                                         'outside the model domain'):
        Plant(PlantConfig(initial_state=[0.0, 0.0, -1.5, 0.5]))


def test_each_reset_starts_the_next_run():
    """The run number the simulator publishes (TsrState.run): 0 at start, one more per reset,
    a refused reset changing nothing."""
    from tsr_sim.plant import config_from_parameters, Plant
    plant = Plant(config_from_parameters({}))
    assert plant.run == 0
    assert plant.reset([0.0, 0.0, -0.5, 0.0]) is None and plant.run == 1
    assert plant.reset([0.0, 0.0, -2.0, 0.0]) is not None and plant.run == 1


def test_a_tether_paid_out_past_twice_its_length_halts_the_run():
    from tsr_sim import dynamics
    from tsr_sim.plant import config_from_parameters, Plant, Status
    plant = Plant(config_from_parameters({'initial_state': [0.0, 0.0, 0.99, 2.0]}))
    for _ in range(10):
        plant.advance(0.0)
    assert plant.status is Status.HALTED_OUT_OF_DOMAIN and 'paid out' in plant.message
    assert plant.state[dynamics.LENGTH_OFFSET] + 1.0 <= dynamics.PLAUSIBLE_LENGTH
