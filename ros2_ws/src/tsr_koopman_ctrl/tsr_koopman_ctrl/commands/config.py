"""Write the controller node's example parameter file from the laws' settings classes.

    ros2 run tsr_koopman_ctrl config > ros2_ws/src/tsr_koopman_ctrl/config/controller.yaml

The file is derived, never edited by hand: a test checks it equals this output.
"""

import argparse
import sys

from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl.control.registry import DEFAULT_LAW, NODE_SECTIONS
from tsr_koopman_ctrl.control.settings import fields

HEADER = """\
# Example parameters for tsr_koopman_ctrl/controller_node (the defaults), written by
# `ros2 run tsr_koopman_ctrl config` from the laws' settings classes: do not edit by hand.
#   ros2 run tsr_koopman_ctrl controller_node --ros-args --params-file controller.yaml
# Keyed /**/tsr_controller: it applies to the node under any namespace. The node declares every
# law's settings and those of the sections around any law: observer (offset-free control, on by
# default), excitation (off by default), supervisor (runtime assurance of a learned law, on by
# default); `law` picks the law.
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
    sections = {law: CONTROLLERS[law].Settings for law in sorted(CONTROLLERS)}
    sections.update(NODE_SECTIONS)
    for law, settings in sections.items():
        lines.append(f'    {law}:')
        for name, default, meta in fields(settings):
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
