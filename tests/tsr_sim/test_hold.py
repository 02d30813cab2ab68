"""The reel hold: what the plant does on its own when its controller stops (dynamics.hold_tension,
Plant.advance(hold=True)), ROS-free."""

import numpy as np
import pytest

from tsr_sim import dynamics
from tsr_sim.plant import config_from_parameters, Plant, Status

#: States of the learned NMPC's deployments where a stop is hardest: the largest librations
#: after the hold (every tenth state of the nine comparison starts' runs, held 30 tau, ranked
#: by their swing), the paper's start, and one reeling in.
DEPLOYMENT_STATES = ([-0.536, -0.788, -0.66, 0.485], [-0.611, -0.704, -0.622, 0.272],
                     [-0.454, -0.847, -0.718, 0.621], [-0.571, 0.719, -0.331, -0.066],
                     [-0.652, 0.642, -0.352, -0.01], [0.0, 0.0, -0.99, 0.5],
                     [0.1, 0.3, -0.6, -0.4])


def test_unclamped_the_hold_decelerates_the_reel_in_proportion_to_its_speed():
    x = np.array([0.2, -0.3, -0.5, 0.4])
    u = dynamics.hold_tension(x, gain=5.0, u_max=np.inf)
    assert dynamics.derivative(x, u)[dynamics.LENGTH_RATE] == pytest.approx(-5.0 * 0.4)


def test_the_hold_never_pushes_nor_passes_the_limit():
    reeling_in = np.array([0.0, 0.0, -0.5, -2.0])
    paying_out = np.array([0.0, 0.0, -0.5, 3.0])
    assert dynamics.hold_tension(reeling_in) == 0.0
    assert dynamics.hold_tension(paying_out) == dynamics.TENSION_LIMIT


@pytest.mark.parametrize('state', DEPLOYMENT_STATES)
def test_held_from_a_deployment_state_the_robot_stays_and_the_tether_stops(state):
    """30 tau under the hold: no halt (domain, tumbling), the swing within 0.9 rad, the reel
    stopped. Constant u = 3 (the former safe tension) loses the first of these states."""
    plant = Plant(config_from_parameters({'initial_state': state}))
    swing = 0.0
    for _ in range(3000):
        plant.advance(0.0, hold=True)
        swing = max(swing, abs(plant.state[dynamics.THETA]))
    assert plant.status is Status.RUNNING and swing < 0.9
    assert abs(plant.state[dynamics.LENGTH_RATE]) < 0.01


def test_the_constant_safe_tension_loses_a_deployment_state_the_hold_keeps():
    plant = Plant(config_from_parameters({'initial_state': DEPLOYMENT_STATES[0]}))
    tension = plant.config.scale.u_to_tension(dynamics.EQUILIBRIUM_TENSION)
    for _ in range(3000):
        plant.advance(tension)
    assert plant.status is Status.HALTED_OUT_OF_DOMAIN


def test_the_hold_acts_on_the_tether_past_the_tension_actuator():
    """A lagging, weak actuator does not slow the hold: it is the reel's own loop."""
    state = DEPLOYMENT_STATES[0]
    nominal = Plant(config_from_parameters({'initial_state': state}))
    weak = Plant(config_from_parameters({'initial_state': state, 'actuator_gain': 0.5,
                                         'actuator_lag': 0.3}))
    for plant in (nominal, weak):
        for _ in range(200):
            plant.advance(0.0, hold=True)
    np.testing.assert_allclose(weak.state, nominal.state, atol=1e-12)


def test_a_plant_without_a_hold_flies_the_tension_it_is_given():
    plant = Plant(config_from_parameters({'initial_state': DEPLOYMENT_STATES[0],
                                          'hold_gain': 0.0}))
    free = Plant(config_from_parameters({'initial_state': DEPLOYMENT_STATES[0]}))
    plant.advance(5.0, hold=True)
    free.advance(5.0)
    np.testing.assert_array_equal(plant.state, free.state)
