"""Write the controller node's example parameter file from the laws' settings classes.

    ros2 run tsr_koopman_ctrl config > ros2_ws/src/tsr_koopman_ctrl/config/controller.yaml

The file is derived, never edited by hand: a test checks it equals this output.
"""

import argparse
import sys

from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl.control.registry import DEFAULT_LAW, settings_sections
from tsr_koopman_ctrl.control.settings import fields

HEADER = """\
# Example parameters for tsr_koopman_ctrl/controller_node (the defaults), written by
# `ros2 run tsr_koopman_ctrl config` from the laws' settings classes: do not edit by hand.
#   ros2 run tsr_koopman_ctrl controller_node --ros-args --params-file controller.yaml
# Keyed /**/tsr_controller: it applies to the node under any namespace. The node declares every
# law's settings and those of the sections around any law (observer: offset-free control;
# excitation: added to the tension; supervisor: runtime assurance of a learned law); `law` picks
# the law.
"""


def scalar(value):
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value
    return repr(float(value)) if isinstance(value, float) else str(value)


def example_yaml(node_name='/**/tsr_controller', default_law=DEFAULT_LAW):
    lines = [HEADER.rstrip('\n'), f'{node_name}:', '  ros__parameters:',
             f'    law: {default_law}   # one of {", ".join(sorted(CONTROLLERS))}',
             '    autostart: true           # configure and activate at start',
             '    state_timeout: 5.0        # s without a state -> safe_tension']
    sections = settings_sections()
    # the laws in name order, then the sections around them
    for section in sorted(CONTROLLERS) + [s for s in sections if s not in CONTROLLERS]:
        lines.append(f'    {section}:')
        for name, default, meta in fields(sections[section]):
            value = (f'[{", ".join(scalar(v) for v in default)}]'
                     if isinstance(default, tuple) else scalar(default))
            lines += [f'      # {meta["description"]}', f'      {name}: {value}']
    return '\n'.join(lines) + '\n'


def main(argv=None):
    description = __doc__.split('\n\n')[0].rstrip('.') + ', to stdout.'
    argparse.ArgumentParser(prog='config', description=description).parse_args(argv)
    sys.stdout.write(example_yaml())
    return 0


if __name__ == '__main__':
    sys.exit(main())
