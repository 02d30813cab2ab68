"""The shipped example parameter files: derived where they can be, and they start their nodes."""

import os
import subprocess

import pytest
import yaml

from tsr_koopman_ctrl.commands.config import example_yaml
from tsr_koopman_ctrl.control.registry import DEFAULT_LAW
from tsr_koopman_ctrl.launcher import executable

from conftest import ROOT

CONFIG = ROOT / 'ros2_ws' / 'src' / 'tsr_koopman_ctrl' / 'config'
SIM_CONFIG = ROOT / 'ros2_ws' / 'src' / 'tsr_sim' / 'config'


def test_controller_config_is_derived_from_the_law_settings():
    """One declaration: the file equals what the settings classes write (regenerate it with
    python -m tsr_koopman_ctrl.commands.config)."""
    assert (CONFIG / 'controller.yaml').read_text() == example_yaml()
    params = yaml.safe_load(example_yaml())['/**/tsr_controller']['ros__parameters']
    from tsr_koopman_ctrl.control import KoopmanMpc, LinearisedLqr
    assert params['koopman_mpc']['horizon'] == KoopmanMpc.Settings().horizon
    assert params['linear_lqr']['q'] == list(LinearisedLqr.Settings().q)


def test_the_sim_and_recorder_configs_are_derived_from_their_schemas():
    """The simulator's and the recorder's files too equal what their schema classes write
    (python -m tsr_koopman_ctrl.commands.config --node sim|recorder)."""
    assert (SIM_CONFIG / 'sim.yaml').read_text() == example_yaml('sim')
    assert (CONFIG / 'recorder.yaml').read_text() == example_yaml('recorder')


def test_recorder_config_records_the_loop_topics():
    from tsr_sim import wire
    params = yaml.safe_load((CONFIG / 'recorder.yaml').read_text())
    assert params['/**/tsr_recorder']['ros__parameters']['topics'] == list(wire.LOOP_TOPIC_TYPES)


def test_the_sim_example_holds_the_simulator_s_names_and_defaults():
    """config/sim.yaml holds the defaults under the simulator's names: a misspelt name there
    would be dropped by ROS without a word."""
    from tsr_sim import dynamics
    from tsr_sim.plant import PLANT_PARAMETERS, SIMULATOR_PARAMETERS
    from tsr_sim.units import Scale
    path = SIM_CONFIG / 'sim.yaml'
    values = yaml.safe_load(path.read_text())['/**/tsr_sim']['ros__parameters']
    scale = Scale()
    defaults = {name: spec[0] for name, spec in {**PLANT_PARAMETERS,
                                                 **SIMULATOR_PARAMETERS}.items()}
    defaults.update(orbit_rate=scale.orbit_rate, tether_length=scale.tether_length,
                    mass=scale.mass, max_tension=scale.u_to_tension(dynamics.TENSION_LIMIT))
    assert set(values) <= set(defaults)
    for name, value in values.items():
        if isinstance(value, str):
            assert value == defaults[name]
        else:
            assert value == pytest.approx(defaults[name], rel=1e-4), name


@pytest.mark.ros
def test_sim_example_params_run_a_lockstep_simulator(ros, start_node):
    from tsr_msgs.msg import TsrState
    from tsr_sim import ros_io, wire
    params = str(ROOT / 'ros2_ws/src/tsr_sim/config/sim.yaml')
    start_node('tsr_sim', 'sim_node', 'tsr_sim', extra_args=['--params-file', params])
    got = []
    ros.node.create_subscription(TsrState, wire.STATE_TOPIC, got.append, ros_io.LOOP_QOS)
    ros.spin_until(lambda: got, what='a state from the example configuration')
    assert abs(got[0].length - 1000.0) < 1e-6 and got[0].step == 0


@pytest.mark.ros
def test_bad_parameters_fail_at_start_with_one_line(ros_domain, ros_namespace):
    for args in (['-p', 'mode:=bogus'], ['-p', 'substeps:=0'], ['-p', 'step:=fast'],
                 ['-p', 'initial_state:=[0.0, 0.0, -1.5, 0.5]']):
        result = subprocess.run([executable('tsr_sim', 'sim_node'), '--ros-args',
                                 '-r', f'__ns:={ros_namespace}', *args],
                                env=dict(os.environ, ROS_DOMAIN_ID=str(ros_domain)),
                                capture_output=True, text=True, timeout=30)
        assert result.returncode == 2, result.stderr
        assert result.stderr.startswith('cannot start:') and 'Traceback' not in result.stderr


@pytest.mark.ros
def test_controller_from_any_directory_commands_the_plant_with_the_shipped_model(
        ros, start_node, tmp_path):
    """The installed executable started elsewhere (as `ros2 run` users do) finds the shipped
    model by name through the ament index, with the example parameter file."""
    from tsr_msgs.msg import SimStatus
    from tsr_sim import ros_io, wire
    elsewhere = tmp_path / 'elsewhere'
    elsewhere.mkdir()
    start_node('tsr_sim', 'sim_node', 'tsr_sim', {'max_steps': 50, 'progress_every': 0})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller', cwd=str(elsewhere),
               extra_args=['--params-file', str(CONFIG / 'controller.yaml')])
    seen = []
    ros.node.create_subscription(SimStatus, wire.SIM_STATUS_TOPIC, seen.append,
                                 ros_io.LATCHED_QOS)
    ros.spin_until(lambda: seen and seen[-1].commands_accepted >= 50, timeout=30.0,
                   what='50 commands of the default law accepted by the simulator')
    last = seen[-1]
    assert last.rejected_non_finite + last.rejected_negative + last.rejected_over_limit == 0
    log = (tmp_path / 'tsr_controller.log').read_text()
    assert f'{DEFAULT_LAW} controller' in log and 'share/tsr_koopman_ctrl/models' in log
