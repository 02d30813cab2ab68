"""The shipped example parameter files start the nodes they are for."""

import os

from tsr_koopman_ctrl.launcher import executable

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_sim_example_params_run_a_lockstep_simulator(ros, start_node):
    from tsr_msgs.msg import TsrState
    from tsr_sim import ros_io
    params = os.path.join(ROOT, 'ros2_ws/src/tsr_sim/config/sim.yaml')
    start_node('tsr_sim', 'sim_node', 'tsr_sim', extra_args=['--params-file', params])
    got = []
    ros.node.create_subscription(TsrState, ros_io.STATE_TOPIC, got.append, ros_io.LOOP_QOS)
    ros.spin_until(lambda: got, what='a state from the example configuration')
    assert abs(got[0].length - 1000.0) < 1e-6 and got[0].step == 0


def test_bad_parameters_fail_at_start_with_one_line(domain_id):
    import subprocess
    for args in (['-p', 'mode:=bogus'], ['-p', 'substeps:=0'], ['-p', 'step:=fast']):
        result = subprocess.run([executable('tsr_sim', 'sim_node'), '--ros-args', *args],
                                env=dict(os.environ, ROS_DOMAIN_ID=str(domain_id)),
                                capture_output=True, text=True, timeout=30)
        assert result.returncode == 2, result.stderr
        assert result.stderr.startswith('cannot start:') and 'Traceback' not in result.stderr


def test_controller_example_params_close_the_loop_with_the_shipped_model(ros, start_node):
    from tsr_msgs.msg import SimStatus
    from tsr_sim import ros_io
    params = os.path.join(ROOT, 'ros2_ws/src/tsr_koopman_ctrl/config/controller.yaml')
    shipped = os.path.join(ROOT, 'models', 'koopman_default')
    start_node('tsr_sim', 'sim_node', 'tsr_sim', {'max_steps': 50, 'progress_every': 0})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               extra_args=['--params-file', params, '-p', f'model:={shipped}'])
    seen = []
    ros.node.create_subscription(SimStatus, ros_io.STATUS_TOPIC, seen.append,
                                 ros_io.LATCHED_QOS)
    ros.spin_until(lambda: seen and seen[-1].commands_accepted >= 50, timeout=30.0,
                   what='50 koopman_mpc commands accepted by the simulator')
    last = seen[-1]
    assert last.rejected_non_finite + last.rejected_negative + last.rejected_over_limit == 0
