"""The controller as a managed node, resets, and health on /diagnostics, over DDS."""

import time

import numpy as np
import pytest
from tsr_sim import dynamics, wire
from tsr_sim.units import Scale

pytestmark = pytest.mark.ros

SCALE = Scale()
UNCONFIGURED, INACTIVE, ACTIVE = 1, 2, 3


class Watch:
    """What the test sees on the loop in `namespace` (default: the test's, where `ros` lives):
    tension commands, simulator statuses, states, and the last /diagnostics status of each
    node."""

    def __init__(self, ros, namespace=None):
        from diagnostic_msgs.msg import DiagnosticArray
        from tsr_msgs.msg import SimStatus, TensionCommand, TsrState
        from tsr_sim import ros_io
        namespace = self.namespace = namespace or ros.namespace
        self.commands, self.states, self.status, self.health = [], {}, None, {}
        self.holds = []                      # the commands' hold flags
        self.runs = [self.states]
        self.run = 0
        node = ros.node

        def on_state(msg):
            if msg.run != self.run:          # a new run, as the simulator numbers them
                self.run, self.states = msg.run, {}
                self.runs.append(self.states)
            self.states[msg.step] = SCALE.state_from_si(wire.state_from_msg(msg))

        def on_command(msg):
            self.commands.append((msg.step, msg.tension))
            self.holds.append(msg.hold)

        node.create_subscription(TensionCommand, wire.resolve(wire.TENSION_TOPIC, namespace),
                                 on_command, ros_io.LOOP_QOS)
        node.create_subscription(TsrState, wire.resolve(wire.STATE_TOPIC, namespace), on_state,
                                 ros_io.LOOP_QOS)
        node.create_subscription(SimStatus, wire.resolve(wire.SIM_STATUS_TOPIC, namespace),
                                 lambda m: setattr(self, 'status', m), ros_io.LATCHED_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self.on_diagnostics, 10)

    def on_diagnostics(self, msg):
        for status in msg.status:
            self.health[status.name] = (status.level, status.message,
                                        {kv.key: kv.value for kv in status.values})


def lifecycle_state(ros, node='tsr_controller'):
    from lifecycle_msgs.srv import GetState
    return ros.call(GetState, f'{node}/get_state', GetState.Request(),
                    resend=2.0).current_state.id


def transition(ros, label, node='tsr_controller'):
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    ids = {'configure': Transition.TRANSITION_CONFIGURE,
           'activate': Transition.TRANSITION_ACTIVATE,
           'deactivate': Transition.TRANSITION_DEACTIVATE,
           'cleanup': Transition.TRANSITION_CLEANUP}
    request = ChangeState.Request(transition=Transition(id=ids[label]))
    return ros.call(ChangeState, f'{node}/change_state', request).success


def health_of(watch, node):
    """The last health a node reported on /diagnostics; a relative name is in the watch's
    namespace."""
    node = wire.resolve(node, watch.namespace)
    return next((h for name, h in watch.health.items() if name.startswith(f'{node}:')), None)


def test_lifecycle_transitions_and_what_the_plant_gets_when_deactivated(ros, start_node):
    """Unconfigured and inactive: no command. Active: commands. Deactivate: the stop once (step
    NO_STEP, hold set), then nothing: the timed simulator engages its reel hold. Cleanup, then a
    bad law set while unconfigured fails configure with one line, on /diagnostics as an
    ERROR."""
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               {'mode': 'timed', 'rate_hz': 50.0, 'command_timeout': 60.0, 'progress_every': 0,
                'clock_start': 'now', 'initial_state': [0.0, 0.0, -0.05, 0.0]})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'law': 'linear_lqr', 'autostart': False})
    watch = Watch(ros)
    ros.spin_until(lambda: health_of(watch, 'tsr_controller') is not None, timeout=30.0,
                   what="the controller's health")
    assert lifecycle_state(ros) == UNCONFIGURED
    level, message, values = health_of(watch, 'tsr_controller')
    assert level == b'\x01' and values['lifecycle_state'] == 'unconfigured'
    ros.spin_until(lambda: watch.status is not None and watch.status.step > 20,
                   what='the timed simulator to run')
    assert watch.commands == []

    assert transition(ros, 'configure') and lifecycle_state(ros) == INACTIVE
    ros.spin_for(1.0)
    assert watch.commands == []          # configured, not commanding
    assert transition(ros, 'activate') and lifecycle_state(ros) == ACTIVE
    # (the command publisher is made at configure: on a busy machine its discovery by this
    # side and the simulator can take seconds)
    ros.spin_until(lambda: len(watch.commands) > 20, timeout=30.0, what='commands once active')
    assert all(step != wire.NO_STEP for step, _ in watch.commands)
    ros.spin_until(lambda: health_of(watch, 'tsr_controller')[0] == b'\x00',
                   what='OK health while commanding', timeout=30.0)

    assert transition(ros, 'deactivate') and lifecycle_state(ros) == INACTIVE
    ros.spin_until(lambda: watch.commands[-1][0] == wire.NO_STEP,
                   what='the safe tension on deactivate', timeout=30.0)
    count = len(watch.commands)
    ros.spin_for(1.5)
    assert len(watch.commands) == count      # then nothing
    assert watch.commands[-1] == (wire.NO_STEP,
                                  pytest.approx(SCALE.u_to_tension(dynamics.EQUILIBRIUM_TENSION)))
    assert watch.holds[-1] and not any(watch.holds[:-1])
    accepted = watch.status.commands_accepted
    ros.spin_until(lambda: watch.status.step > 100 and watch.status.holding,
                   what='the simulator holding it', timeout=30.0)
    assert watch.status.commands_accepted == accepted and watch.status.command_timeouts == 0

    # Read at configure: refused while configured, accepted unconfigured, applied there.
    (refused,) = ros.set_parameters('tsr_controller', {'law': 'pid'})
    assert not refused[0] and 'read at configure' in refused[1]
    assert transition(ros, 'cleanup') and lifecycle_state(ros) == UNCONFIGURED
    assert ros.set_parameters('tsr_controller', {'law': 'pid'}) == [(True, '')]
    assert not transition(ros, 'configure') and lifecycle_state(ros) == UNCONFIGURED
    ros.spin_until(lambda: health_of(watch, 'tsr_controller')[0] == b'\x02',
                   what='an ERROR on /diagnostics', timeout=30.0)
    assert "unknown law 'pid'" in health_of(watch, 'tsr_controller')[1]


def test_a_reset_run_repeats_the_first(ros, start_node):
    """The default law (koopman_nmpc, warm-started from its last plan, offset-free: an
    observer with memory) from the paper's start, then `tsr/reset` back to it: the controller
    sees the step go back, resets the law and its observer, and the second run repeats the
    first within 1e-6."""
    from tsr_msgs.srv import ResetSim
    steps = 200
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               {'max_steps': steps, 'progress_every': 0, 'wait_for_subscribers': 2})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'wait_for_subscribers': 1})
    watch = Watch(ros)
    ros.spin_until(lambda: steps in watch.states, timeout=60.0, what='the first run')
    si = SCALE.state_to_si(dynamics.PAPER_INITIAL_STATE)
    response = ros.call(ResetSim, wire.RESET_SERVICE,
                        ResetSim.Request(theta=si[0], theta_rate=si[1], length=si[2],
                                         length_rate=si[3]))
    assert response.success, response.message
    ros.spin_until(lambda: len(watch.runs) == 2 and steps in watch.runs[1], timeout=60.0,
                   what='the second run')
    first, second = watch.runs
    assert sorted(first) == sorted(second) == list(range(steps + 1))
    np.testing.assert_allclose([second[k] for k in range(steps + 1)],
                               [first[k] for k in range(steps + 1)], rtol=0, atol=1e-6)
    assert max(abs(first[k][dynamics.THETA]) for k in first) > 0.1    # it did swing


def test_a_tumbling_run_halts_and_every_node_reports_health(ros, start_node, tmp_path):
    """A swing past max_swing halts the simulator as leaving the domain does: an ERROR on
    /diagnostics, where the controller and the recorder report too."""
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               {'max_swing': 0.05, 'progress_every': 0, 'wait_for_subscribers': 2})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'law': 'linear_lqr', 'wait_for_subscribers': 1})
    start_node('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
               {'output_dir': str(tmp_path), 'bag_name': 'tumble'})
    watch = Watch(ros)
    ros.spin_until(lambda: watch.status is not None and watch.status.status == 1,
                   timeout=60.0, what='the tumbling halt')
    assert 'tumbling' in watch.status.message
    ros.spin_until(lambda: (health_of(watch, 'tsr_sim') or (None,))[0] == b'\x02',
                   what="the simulator's ERROR")
    assert 'tumbling' in health_of(watch, 'tsr_sim')[1]
    # The controller's first report may come before its first command: wait for one after.
    ros.spin_until(lambda: health_of(watch, 'tsr_recorder') is not None
                   and int((health_of(watch, 'tsr_controller') or (0, '', {}))[2].get(
                       'commands', 0)) >= 1,
                   what="the other nodes' health")
    _, _, recorded = health_of(watch, 'tsr_recorder')
    state_topic = wire.resolve(wire.STATE_TOPIC, ros.namespace)
    assert int(recorded[f'count {state_topic}']) >= 1 and 'bag' in recorded
    _, _, control = health_of(watch, 'tsr_controller')
    assert control['law'] == 'linear_lqr' and int(control['commands']) >= 1
    assert float(control['compute_median_ms']) > 0.0


def test_watchdogs_run_on_sim_time_without_a_clock(ros, start_node):
    """With use_sim_time and no /clock, the controller's state timeout still fires (a steady
    timer), and the simulator on sim time still runs its loop (it is the clock)."""
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'law': 'linear_lqr', 'state_timeout': 0.3, 'use_sim_time': True})
    watch = Watch(ros)
    ros.spin_until(lambda: len(watch.commands) >= 2, timeout=30.0,
                   what='safe tensions on sim time with no clock')
    assert {step for step, _ in watch.commands} == {wire.NO_STEP}


def test_help_starts_no_node(tmp_path):
    import os
    import subprocess
    from tsr_koopman_ctrl.launcher import executable
    for package, exe in (('tsr_sim', 'sim_node'), ('tsr_koopman_ctrl', 'controller_node'),
                         ('tsr_koopman_ctrl', 'recorder_node')):
        start = time.monotonic()
        result = subprocess.run([executable(package, exe), '--help'], cwd=tmp_path,
                                capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        assert 'usage:' in result.stdout and '--ros-args' in result.stdout
        assert time.monotonic() - start < 30
    assert os.listdir(tmp_path) == []          # the recorder made no bag
