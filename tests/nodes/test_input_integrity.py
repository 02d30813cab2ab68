"""Input integrity, over DDS between processes, in a real run: what another node on the domain
sends on tsr/state in the middle of it (a plausible state of a run the simulator never started,
a non-finite state, a negative length) is refused and counted on /diagnostics in lockstep and
timed mode, and never reaches the law: no reset, the commands those of the run without it. A
restarted simulator starts a new run."""

import math

import numpy as np
import pytest
from tsr_sim import dynamics, wire
from tsr_sim.units import Scale

pytestmark = pytest.mark.ros

SCALE = Scale()
#: The plant's actuator is weaker than the law's model: the observer learns the difference, so
#: a reset of the law mid-run changes most of the commands after it (ROS-free: 153 of 200).
WEAK_ACTUATOR = 0.8
#: A run the simulator never started, and a step far from any it reaches.
FORGED_RUN, FORGED_STEP = 7, 10 ** 6
#: A timed simulator applies its safe tension until the first command: near the target it
#: holds the tether.
NEAR_TARGET = [0.0, 0.0, -0.05, 0.0]


class Loop:
    """What this side sees of the loop: the simulator's own states (run 0, finite, l > 0: this
    side's forged ones are none of them), the first command answering each step, the
    simulator's status and the controller's last /diagnostics values; and a second writer of
    states, as another node on the domain would have."""

    def __init__(self, ros):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from tsr_msgs.msg import SimStatus, TensionCommand, TsrState
        from tsr_sim import ros_io
        self.ros = ros
        self.states, self.commands, self.status, self.controller = {}, {}, None, {}
        # Deep enough that this side, on a busy machine, keeps every message of a lockstep run.
        everything = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE,
                                history=HistoryPolicy.KEEP_LAST)
        node = ros.node
        node.create_subscription(TsrState, wire.STATE_TOPIC, self.on_state, everything)
        node.create_subscription(TensionCommand, wire.TENSION_TOPIC, self.on_command,
                                 everything)
        node.create_subscription(SimStatus, wire.SIM_STATUS_TOPIC,
                                 lambda m: setattr(self, 'status', m), ros_io.LATCHED_QOS)
        node.create_subscription(DiagnosticArray, ros_io.DIAGNOSTICS_TOPIC,
                                 self.on_diagnostics, 10)
        self.forger_readers = ros_io.MatchedReaders()
        self.forger = node.create_publisher(TsrState, wire.STATE_TOPIC, ros_io.LOOP_QOS,
                                            event_callbacks=self.forger_readers.callbacks)
        self.controller_name = wire.resolve('tsr_controller', ros.namespace)

    def on_state(self, msg):
        si = wire.state_from_msg(msg, dynamics.PLANAR_DIM)
        if msg.run == 0 and np.all(np.isfinite(si)) and si[dynamics.LENGTH_OFFSET] > 0:
            self.states.setdefault(msg.step, si)

    def on_command(self, msg):
        if msg.step != wire.NO_STEP:
            self.commands.setdefault(msg.step, msg.tension)

    def on_diagnostics(self, msg):
        for status in msg.status:
            if status.name.startswith(f'{self.controller_name}:'):
                self.controller = {kv.key: kv.value for kv in status.values}

    def reported(self, key):
        """An integer the controller last reported on /diagnostics (-1: none yet)."""
        value = self.controller.get(key, '')
        return int(value) if value not in ('', None) else -1

    def forge(self):
        """Another node's states, back to back: a plausible one of a run the simulator never
        started (l = 1000 m at rest), a non-finite one and a negative length."""
        def state(x, run):
            return wire.state_to_msg(np.asarray(x, dtype=float), FORGED_STEP,
                                     self.ros.node.get_clock().now().to_msg(), run=run)
        for msg in (state([0.0, 0.0, 1000.0, 0.0], FORGED_RUN),
                    state([math.nan] * 4, 0),
                    state([0.0, 0.0, -5000.0, 0.0], 0)):
            self.forger.publish(msg)

    def counted(self):
        return {key: self.reported(key)
                for key in ('runs', 'foreign_states', 'non_finite_states', 'refused_states')}


def forge_in_the_middle_of_the_run(ros, loop, after=30):
    """Once the controller and this side read the forger (matched at the DDS level: a state
    published before would be lost) and the loop has answered `after` steps: the forged states;
    the step reached by then."""
    ros.spin_until(lambda: loop.forger_readers.count >= 2 and len(loop.commands) > after,
                   timeout=60.0, what=f'{after} steps of the loop, the forger matched')
    loop.forge()
    return max(loop.commands)


def test_forged_states_in_a_lockstep_run_are_counted_and_change_no_command(ros, start_node):
    """The commands of the whole run are those the law gives, ROS-free, for the simulator's
    states alone: the forged states never reached the law or its observer."""
    from tsr_koopman_ctrl.control import make_controller, TensionLimiter
    from tsr_koopman_ctrl.control.step import ControlStep
    steps = 600
    loop = Loop(ros)
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               {'mode': 'lockstep', 'actuator_gain': WEAK_ACTUATOR, 'max_steps': steps,
                'progress_every': 0, 'wait_for_subscribers': 2})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'law': 'linear_lqr', 'wait_for_subscribers': 2})
    forged_at = forge_in_the_middle_of_the_run(ros, loop)
    ros.spin_until(lambda: loop.reported('last_step') >= steps - 1
                   and all(k in loop.commands and k in loop.states for k in range(steps)),
                   timeout=60.0, what=f'the {steps} steps of the run answered and reported')
    assert loop.counted() == {'runs': 0, 'foreign_states': 1, 'non_finite_states': 1,
                              'refused_states': 1}

    replay = ControlStep(make_controller('linear_lqr'), TensionLimiter(dynamics.TENSION_LIMIT))
    replay.reset()
    want = [replay(SCALE.state_from_si(loop.states[k])).tension for k in range(steps)]
    got = [SCALE.tension_to_u(loop.commands[k]) for k in range(steps)]
    differing = [k for k in range(steps) if abs(got[k] - want[k]) > 1e-9]
    assert not differing, (f'{len(differing)} commands differ from the run without the forged '
                           f'states (forged once this side saw step {forged_at}), the first at '
                           f'step {differing[0]}')


def test_forged_states_in_a_timed_run_are_counted_and_reset_nothing(ros, start_node):
    loop = Loop(ros)
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               {'mode': 'timed', 'rate_hz': 50.0, 'initial_state': NEAR_TARGET,
                'progress_every': 0})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller', {'law': 'linear_lqr'})
    forged_at = forge_in_the_middle_of_the_run(ros, loop, after=20)
    ros.spin_until(lambda: loop.reported('last_step') > forged_at + 50, timeout=30.0,
                   what=f'a report of the controller past step {forged_at + 50}')
    assert loop.counted() == {'runs': 0, 'foreign_states': 1, 'non_finite_states': 1,
                              'refused_states': 1}


def test_a_restarted_simulator_is_commanded_as_a_new_run(ros, start_node):
    """The simulator stopped and started again (its run 0 from step 0, the run number the
    controller flew): once the old one has been silent for state_timeout, the new one's states
    start a new run and are answered."""
    params = {'mode': 'timed', 'rate_hz': 50.0, 'initial_state': NEAR_TARGET,
              'progress_every': 0}
    loop = Loop(ros)
    first = start_node('tsr_sim', 'sim_node', 'tsr_sim', params)
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'law': 'linear_lqr', 'state_timeout': 0.5})
    ros.spin_until(lambda: loop.status is not None and loop.status.commands_accepted > 20,
                   timeout=60.0, what='the first simulator commanded')
    first.stop()
    ros.spin_for(0.5)                # the first simulator's last messages
    loop.status = None
    start_node('tsr_sim', 'sim_node', 'tsr_sim', params)
    ros.spin_until(lambda: loop.status is not None and loop.status.commands_accepted > 20,
                   timeout=30.0, what='the restarted simulator commanded')
    ros.spin_until(lambda: loop.reported('runs') == 1, timeout=10.0,
                   what='the new run on /diagnostics')
    assert loop.reported('foreign_states') == 0
