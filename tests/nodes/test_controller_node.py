"""The controller node as a separate process: timeouts on both sides, restart, bad models."""

import pytest
from tsr_sim import wire
from tsr_sim.units import Scale

pytestmark = pytest.mark.ros


SCALE = Scale()
SAFE_U = 3.0


def watch_loop(ros):
    """Record the simulator's status and every tension command seen on the wire."""
    from tsr_msgs.msg import SimStatus, TensionCommand
    from tsr_sim import ros_io
    seen = {'status': None, 'commands': []}
    ros.node.create_subscription(SimStatus, wire.SIM_STATUS_TOPIC,
                                 lambda m: seen.__setitem__('status', m), ros_io.LATCHED_QOS)
    ros.node.create_subscription(TensionCommand, wire.TENSION_TOPIC,
                                 lambda m: seen['commands'].append(m.tension), ros_io.LOOP_QOS)
    return seen


def test_killing_the_controller_trips_both_timeouts_and_a_restart_resumes(ros, start_node):
    controller_params = {'controller': 'linear_lqr', 'state_timeout': 0.5}
    sim = start_node('tsr_sim', 'sim_node', 'tsr_sim',
                     {'mode': 'timed', 'rate_hz': 50.0, 'command_timeout': 0.3,
                      'progress_every': 0, 'max_steps': 100_000})
    first = start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
                       controller_params)
    seen = watch_loop(ros)
    status = lambda: seen['status']  # noqa: E731
    ros.spin_until(lambda: status() is not None and status().commands_accepted > 20,
                   timeout=30.0, what='the controller to drive the simulator')
    first.kill()
    accepted = status().commands_accepted
    timeouts = status().command_timeouts
    # Simulator side: no command for command_timeout -> safe tension, counted.
    ros.spin_until(lambda: status().command_timeouts > timeouts, what='a command timeout')
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller', controller_params)
    ros.spin_until(lambda: status().commands_accepted > accepted + 20, timeout=30.0,
                   what='the restarted controller to resume control')
    # Controller side: the simulator stops -> after state_timeout, the safe tension.
    sim.kill()
    seen['commands'].clear()
    ros.spin_until(lambda: len(seen['commands']) >= 2, timeout=10.0,
                   what='safe commands after the states stopped')
    assert seen['commands'][-1] == pytest.approx(SCALE.u_to_tension(SAFE_U))


@pytest.mark.parametrize('params, message', [
    ({'controller': 'koopman_lqr', 'koopman_lqr': {'model': '/nonexistent/model'}},
     '/nonexistent/model: no such model directory'),
    ({'controller': 'koopman_mpc', 'koopman_mpc': {'horizon': 0}},
     'koopman_mpc.horizon'),
    ({'controller': 'linear_lqr', 'linear_lqr': {'q': [1.0, 2.0]}},
     'linear_lqr.q needs 4 numbers'),
    ({'controller': 'pid'}, "unknown controller 'pid'")])
def test_bad_controller_configuration_fails_at_start_with_one_line(start_node, tmp_path,
                                                                   params, message):
    proc = start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller', params)
    assert proc.wait(timeout=30) == 2
    log = (tmp_path / 'tsr_controller.log').read_text()
    assert message in log and 'Traceback' not in log
    assert log.count('cannot start:') == 1
