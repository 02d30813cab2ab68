"""The simulator node as a separate process, driven over DDS by a test node."""

import math

import numpy as np
import pytest

from tsr_sim import dynamics, wire
from tsr_sim.units import Scale

pytestmark = pytest.mark.ros


SCALE = Scale()
SIM_PARAMS = {'mode': 'lockstep', 'substeps': 10, 'max_tension': SCALE.u_to_tension(5.0),
              'republish_period': 0.2, 'progress_every': 0}


def tension_law(x):
    """A fixed feedback law (dimensionless) that keeps the paper's start inside the domain."""
    return float(np.clip(3.0 * (1.0 + x[2]) + 2.0 * x[2] - x[3] + 0.5 * x[0], 0.0, 5.0))


class SimDriver:
    """Test-side controller: answers every state with tension_law, records what it sees."""

    def __init__(self, ros, answer=True, namespace=None):
        """namespace: the simulator's (default: the test's, where `ros` lives)."""
        from tsr_msgs.msg import SimStatus, TensionCommand, TsrState
        from tsr_sim import ros_io
        self.ros, self.answer = ros, answer
        namespace = namespace or ros.namespace
        self.states = {}
        self.status = None
        node = ros.node
        self.cmd_pub = node.create_publisher(
            TensionCommand, wire.resolve(wire.TENSION_TOPIC, namespace), ros_io.LOOP_QOS)
        node.create_subscription(TsrState, wire.resolve(wire.STATE_TOPIC, namespace),
                                 self.on_state, ros_io.LOOP_QOS)
        node.create_subscription(SimStatus, wire.resolve(wire.SIM_STATUS_TOPIC, namespace),
                                 lambda m: setattr(self, 'status', m), ros_io.LATCHED_QOS)

    def on_state(self, msg):
        x = SCALE.state_from_si(wire.state_from_msg(msg))
        self.states[msg.step] = x
        if self.answer:
            self.send(SCALE.u_to_tension(tension_law(x)), msg.step)

    def send(self, tension, step):
        self.cmd_pub.publish(wire.tension_msg(tension, step,
                                              self.ros.node.get_clock().now().to_msg()))

    def wait_for_sim(self):
        self.ros.spin_until(lambda: self.cmd_pub.get_subscription_count() > 0 and self.states,
                            timeout=30.0, what='the simulator to appear')


def test_lockstep_trajectory_matches_the_dynamics_module(ros, start_node):
    steps = 150
    start_node('tsr_sim', 'sim_node', 'tsr_sim', dict(SIM_PARAMS, max_steps=steps))
    driver = SimDriver(ros)
    driver.wait_for_sim()
    driver.send(SCALE.u_to_tension(tension_law(driver.states[0])), 0)  # in case 0 came early
    ros.spin_until(lambda: steps in driver.states, timeout=60, what=f'{steps} steps')

    x = dynamics.PAPER_INITIAL_STATE.copy()
    for k in range(steps + 1):
        np.testing.assert_allclose(driver.states[k], x, rtol=0, atol=1e-9,
                                   err_msg=f'step {k}')
        x = dynamics.rk4_step(x, tension_law(x), 0.01, 10)
    ros.spin_until(lambda: driver.status is not None and driver.status.status == 2,
                   what='FINISHED status')
    assert driver.status.step == steps
    # The second answer to step 0 above is a copy of the accepted one: dropped, not a
    # rejection (what a controller sends back when the simulator republishes a state).
    assert driver.status.rejected_stale == 0


def test_bad_commands_are_rejected_and_counted(ros, start_node):
    """...and the controller's safe tension, which answers no state, is neither applied nor
    counted as a rejection."""
    start_node('tsr_sim', 'sim_node', 'tsr_sim', SIM_PARAMS)
    driver = SimDriver(ros, answer=False)
    driver.wait_for_sim()
    limit = SIM_PARAMS['max_tension']
    for tension, step in [(math.nan, 0), (math.inf, 0), (-1.0, 0), (limit * 1.01, 0),
                          (1.0, 5)]:
        driver.send(tension, step)

    def counted():
        s = driver.status
        return s is not None and (s.rejected_non_finite, s.rejected_negative,
                                  s.rejected_over_limit, s.rejected_stale) == (2, 1, 1, 1)
    ros.spin_until(counted, what='rejections counted')
    assert driver.status.commands_accepted == 0 and driver.status.step == 0
    # The safe tension, then one more bad command: its status shows what the first did.
    driver.send(SCALE.u_to_tension(3.0), wire.NO_STEP)
    driver.send(math.nan, 0)
    ros.spin_until(lambda: driver.status.rejected_non_finite == 3, what='the third NaN')
    assert (driver.status.rejected_stale, driver.status.commands_accepted,
            driver.status.step) == (1, 0, 0)
    driver.states.clear()
    driver.send(1.0, 0)                      # a valid command still works afterwards
    ros.spin_until(lambda: 1 in driver.states, what='step 1')


def test_reset_service_restarts_from_the_requested_state(ros, start_node):
    from tsr_msgs.srv import ResetSim
    start_node('tsr_sim', 'sim_node', 'tsr_sim', SIM_PARAMS)
    driver = SimDriver(ros)
    driver.wait_for_sim()
    ros.spin_until(lambda: 20 in driver.states, what='20 steps')
    driver.answer = False
    ros.spin_for(0.3)

    client = ros.node.create_client(ResetSim, wire.RESET_SERVICE)    # the test's namespace
    assert client.wait_for_service(timeout_sec=10.0)
    target = np.array([0.1, -0.2, -0.5, 0.3])
    si = SCALE.state_to_si(target)
    request = ResetSim.Request(theta=si[0], theta_rate=si[1], length=si[2], length_rate=si[3])
    driver.states.clear()
    future = client.call_async(request)
    ros.spin_until(future.done, what='reset response')
    assert future.result().success, future.result().message
    ros.spin_until(lambda: 0 in driver.states, what='state after reset')
    np.testing.assert_allclose(driver.states[0], target, atol=1e-12)

    bad = client.call_async(ResetSim.Request(length=-5.0))
    ros.spin_until(bad.done, what='second reset response')
    assert not bad.result().success
    assert 'outside the model domain' in bad.result().message


def test_a_timed_run_waits_for_its_first_command_and_holds_without_commands(ros, start_node):
    """By default (`clock_start: command`) a timed run does not move before its controller
    answers its first state; started at once, a plant that gets no command engages its reel
    hold after command_timeout (counted): the tether stops paying out."""
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               dict(SIM_PARAMS, mode='timed', rate_hz=200.0, command_timeout=0.2,
                    initial_state=[0.0, 0.0, -0.5, 0.3]))
    driver = SimDriver(ros, answer=False)
    driver.wait_for_sim()
    ros.spin_for(1.0)
    assert max(driver.states) == 0 and driver.status.step == 0
    start_node('tsr_sim', 'sim_node', 'tsr_sim_now',
               dict(SIM_PARAMS, mode='timed', rate_hz=200.0, command_timeout=0.2,
                    clock_start='now', initial_state=[0.0, 0.0, -0.5, 0.3]),
               namespace=f'{ros.namespace}_now')
    now = SimDriver(ros, answer=False, namespace=f'{ros.namespace}_now')
    ros.spin_until(lambda: now.status is not None and now.status.holding
                   and now.status.command_timeouts == 1, what='the hold on a command timeout')
    ros.spin_until(lambda: now.states and max(now.states) > 200, what='time to advance held')
    x = now.states[max(now.states)]
    assert abs(x[dynamics.LENGTH_RATE]) < 1e-3 and now.status.command_timeouts == 1


def test_the_node_declares_the_parameters_of_the_tables_and_nothing_else(ros, start_node):
    """The simulator's names are known without ROS (`tsr_sim.plant`'s tables, which plant
    files and config/sim.yaml are checked against); the running node, asked over its parameter
    service, declares the same ones and rclpy's own two."""
    from rcl_interfaces.srv import ListParameters
    from tsr_sim.plant import PLANT_PARAMETERS, SCALE_PARAMETERS, SIMULATOR_PARAMETERS
    start_node('tsr_sim', 'sim_node', 'tsr_sim', SIM_PARAMS)
    client = ros.node.create_client(ListParameters, 'tsr_sim/list_parameters')
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(ListParameters.Request())
    ros.spin_until(future.done, what='the parameter list')
    declared = set(future.result().result.names)
    assert declared == {*PLANT_PARAMETERS, *SCALE_PARAMETERS, *SIMULATOR_PARAMETERS,
                        'threads', 'thread_priority', 'use_sim_time',
                        'start_type_description_service'}


def test_a_given_name_close_to_a_declared_one_is_warned_of(start_node, tmp_path):
    """ROS drops a parameter a node does not declare: `mas: 22` would simulate the nominal
    mass without a word. A name close to a declared one is a warning; other nodes' names (a
    shared /** file) and dotted names stay quiet."""
    import time
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               dict(SIM_PARAMS, mas=22.0, state_timeout=1.0, koopman_mpc={'horizon': 8},
                    mas_={'s': 1.0}))       # 'mas_.s' is as close to 'mass' as 'mas' is
    log = tmp_path / 'tsr_sim.log'
    deadline = time.monotonic() + 30.0
    while 'did you mean' not in (text := log.read_text() if log.exists() else ''):
        assert time.monotonic() < deadline, f'no warning in the log:\n{text}'
        time.sleep(0.2)
    time.sleep(0.5)     # the node warns of every name at once: any other would follow now
    text = log.read_text()
    assert "parameter 'mas' is not one of this node's and was ignored (did you mean " \
        "'mass'?)" in text
    assert 'state_timeout' not in text and 'koopman_mpc' not in text and 'mas_.s' not in text
