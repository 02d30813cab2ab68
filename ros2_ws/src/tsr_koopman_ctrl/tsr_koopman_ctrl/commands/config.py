"""Write a node's example parameter file from its schema classes (`tsr_sim.schema`).

    ros2 run tsr_koopman_ctrl config > ros2_ws/src/tsr_koopman_ctrl/config/controller.yaml
    ros2 run tsr_koopman_ctrl config --node sim > ros2_ws/src/tsr_sim/config/sim.yaml
    ros2 run tsr_koopman_ctrl config --node recorder > \\
        ros2_ws/src/tsr_koopman_ctrl/config/recorder.yaml

The files are derived, never edited by hand: a test checks each equals this output. The
process parameters every node has (`threads`, `thread_priority`) are left out.
"""

import argparse
import sys

from tsr_sim import dynamics
from tsr_sim.node_parameters import ScaleSettings, SimulatorNodeSettings
from tsr_sim.plant import PlantSettings
from tsr_sim.schema import parameter_lines
from tsr_sim.units import Scale

from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl.control.registry import settings_sections
from tsr_koopman_ctrl.nodes.controller_parameters import ControllerNodeSettings
from tsr_koopman_ctrl.nodes.recorder_parameters import RecorderNodeSettings

HEADER = """\
# Example parameters for {package}/{executable} (the defaults), written by
# `ros2 run tsr_koopman_ctrl config{option}` from the node's schema classes: do not edit by hand.
#   ros2 run {package} {executable} --ros-args --params-file {file}
# Keyed /**/{node}: it applies to the node under any namespace.
"""
CONTROLLER_HEADER = """\
# The node declares every law's settings and those of the sections around any law (observer:
# offset-free control; excitation: added to the tension; supervisor: runtime assurance of a
# learned law; safety_filter: the predictive safety filter); `law` picks the law.
"""
SIMULATOR_HEADER = """\
# A commented-out default is computed from the units: give a value to fix it.
"""


def header(package, executable, node, file, option='', more=''):
    return (HEADER.format(package=package, executable=executable, node=node, file=file,
                          option=option) + more).rstrip('\n').split('\n')


def controller_lines(node_name):
    lines = [*header('tsr_koopman_ctrl', 'controller_node', 'tsr_controller', 'controller.yaml',
                     more=CONTROLLER_HEADER),
             f'{node_name}:', '  ros__parameters:',
             *parameter_lines(ControllerNodeSettings, '    '),
             *parameter_lines(ScaleSettings, '    ')]
    sections = settings_sections()
    # the laws in name order, then the sections around them
    for section in sorted(CONTROLLERS) + [s for s in sections if s not in CONTROLLERS]:
        lines.append(f'    {section}:')
        lines += parameter_lines(sections[section], '      ')
    return lines


def simulator_lines(node_name):
    scale = Scale()
    computed = {
        'max_tension': f'{scale.u_to_tension(dynamics.TENSION_LIMIT):.5g}   # u = '
                       f'{dynamics.TENSION_LIMIT:g} at the default units',
        'safe_tension': f'{scale.u_to_tension(dynamics.EQUILIBRIUM_TENSION):.5g}   # u = '
                        f'{dynamics.EQUILIBRIUM_TENSION:g} at the default units'}
    return [*header('tsr_sim', 'sim_node', 'tsr_sim', 'sim.yaml', ' --node sim',
                    SIMULATOR_HEADER),
            f'{node_name}:', '  ros__parameters:',
            *parameter_lines(SimulatorNodeSettings, '    ', computed),
            *parameter_lines(PlantSettings, '    '),
            *parameter_lines(ScaleSettings, '    ')]


def recorder_lines(node_name):
    return [*header('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder', 'recorder.yaml',
                    ' --node recorder'),
            f'{node_name}:', '  ros__parameters:',
            *parameter_lines(RecorderNodeSettings, '    ')]


#: node -> (its lines, its node name in the file)
NODES = {'controller': (controller_lines, '/**/tsr_controller'),
         'sim': (simulator_lines, '/**/tsr_sim'),
         'recorder': (recorder_lines, '/**/tsr_recorder')}


def example_yaml(node='controller', node_name=None):
    """The example parameter file of `node` (controller, sim or recorder), keyed `node_name`
    (default: /**/<its node name>, for any namespace)."""
    lines, default_name = NODES[node]
    return '\n'.join(lines(node_name or default_name)) + '\n'


def main(argv=None):
    description = __doc__.split('\n\n')[0].rstrip('.') + ', to stdout.'
    parser = argparse.ArgumentParser(prog='config', description=description)
    parser.add_argument('--node', choices=sorted(NODES), default='controller',
                        help='whose file (default: controller)')
    args = parser.parse_args(argv)
    sys.stdout.write(example_yaml(args.node))
    return 0


if __name__ == '__main__':
    sys.exit(main())
