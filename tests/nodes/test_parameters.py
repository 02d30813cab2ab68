"""Parameters as ROS users set them: the shipped files under a namespace, set_parameters on
running nodes (applied or refused with a reason), ranges on every number."""

import pathlib

import pytest
import yaml
from tsr_sim import wire

from conftest import ROOT

pytestmark = pytest.mark.ros

SHIPPED = {'tsr_sim': ROOT / 'ros2_ws/src/tsr_sim/config/sim.yaml',
           'tsr_controller': ROOT / 'ros2_ws/src/tsr_koopman_ctrl/config/controller.yaml',
           'tsr_recorder': ROOT / 'ros2_ws/src/tsr_koopman_ctrl/config/recorder.yaml'}
EXECUTABLES = {'tsr_sim': ('tsr_sim', 'sim_node'),
               'tsr_controller': ('tsr_koopman_ctrl', 'controller_node'),
               'tsr_recorder': ('tsr_koopman_ctrl', 'recorder_node')}


def shipped_copy(node, tmp_path, **changes):
    """The shipped parameter file of `node`, as written (same keys), with `changes`."""
    document = yaml.safe_load(SHIPPED[node].read_text())
    (key,) = document
    document[key]['ros__parameters'].update(changes)
    path = tmp_path / f'{node}.yaml'
    path.write_text(yaml.safe_dump(document))
    return str(path)


def test_the_shipped_files_apply_under_a_namespace(ros, start_node, tmp_path):
    """Keyed /**/<node>, each shipped file applies to its node started under a namespace (rcl
    matches a bare node name only to the node in the root namespace)."""
    namespace = ros.namespace
    bags = tmp_path / 'bags'
    changes = {'tsr_sim': {'mass': 21.0}, 'tsr_controller': {'law': 'linear_lqr'},
               'tsr_recorder': {'output_dir': str(bags), 'bag_name': 'namespaced'}}
    for node, values in changes.items():
        start_node(*EXECUTABLES[node], node, namespace=namespace,
                   extra_args=['--params-file', shipped_copy(node, tmp_path, **values)])
    for node, values in changes.items():
        assert ros.get_parameters(f'{namespace}/{node}', list(values)) == values, node
    # The controller runs the law its file names, the recorder writes where its file says.
    from tsr_msgs.msg import ControllerStatus
    from tsr_sim import ros_io
    statuses = []
    ros.node.create_subscription(ControllerStatus,
                                 wire.resolve(wire.CONTROLLER_STATUS_TOPIC, namespace),
                                 statuses.append, ros_io.LOOP_QOS)
    # The loop runs freely (no max_steps): any status of a computed command will do.
    ros.spin_until(lambda: any(s.controller == 'linear_lqr' and s.status == 0
                               for s in statuses),
                   timeout=60.0, what='the namespaced loop to run the file\'s law')
    assert (bags / 'namespaced' / 'metadata.yaml').exists()


def test_set_parameters_are_applied_or_refused(ros, start_node, tmp_path):
    """Live: the controller's clamp (the commands change), the simulator's progress and the
    recorder's flush period. Refused with a reason: what shapes the plant or the bag
    (read-only), and the law while the controller is active."""
    from tsr_msgs.msg import TensionCommand
    from tsr_sim import ros_io
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               {'progress_every': 0, 'wait_for_subscribers': 1})
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'law': 'linear_lqr', 'observer': {'disturbance': 'none'}})
    start_node('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
               {'output_dir': str(tmp_path / 'bags')})
    commands = []
    ros.node.create_subscription(TensionCommand, wire.TENSION_TOPIC,
                                 lambda m: commands.append(m.tension), ros_io.LOOP_QOS)
    ros.spin_until(lambda: len(commands) > 50, timeout=30.0, what='the loop to run')
    assert max(commands) > 1.5       # linear_lqr from the paper's start: up to ~8.7 N

    # The safe tension must stay within the clamp: lowered first, then the clamp.
    assert ros.set_parameters('tsr_controller', {'max_tension': 1.0})[0][0] is False
    assert ros.set_parameters('tsr_controller', {'safe_tension': 1.0}) == [(True, '')]
    assert ros.set_parameters('tsr_controller', {'max_tension': 1.0}) == [(True, '')]
    # Commands already on the wire when the clamp changed may still arrive: wait for the first
    # one at the new clamp, then every later one stays within it.
    commands.clear()
    ros.spin_until(lambda: any(c == pytest.approx(1.0) for c in commands),
                   what='a command at the new clamp')
    commands.clear()
    ros.spin_until(lambda: len(commands) > 50, what='commands after the new clamp')
    assert max(commands) <= 1.0

    refused = {
        'tsr_controller': {'law': 'nonsense_law', 'safe_tension': 5.0},  # > max_tension
        'tsr_sim': {'mass': 21.0, 'mode': 'timed'},
        'tsr_recorder': {'output_dir': str(tmp_path / 'elsewhere')}}
    for node, values in refused.items():
        for name, value in values.items():
            ((successful, reason),) = ros.set_parameters(node, {name: value})
            assert not successful and reason, (node, name)
            assert ros.get_parameters(node, [name])[name] != value
    ((_, reason),) = ros.set_parameters('tsr_sim', {'mass': 21.0})
    assert 'read-only' in reason
    ((_, reason),) = ros.set_parameters('tsr_controller', {'law': 'nonsense_law'})
    assert 'read at configure' in reason
    for node, values in {'tsr_sim': {'progress_every': 7},
                         'tsr_recorder': {'flush_period': 0.5}}.items():
        assert ros.set_parameters(node, values) == [(True, '')] * len(values)
        assert ros.get_parameters(node, list(values)) == values
    assert not (tmp_path / 'elsewhere').exists()


#: A sample of each: read-only on a running node, and set on one (live, or at configure).
EXPECTED_READ_ONLY = {'tsr_sim': {'mass', 'mode', 'initial_state', 'max_swing'},
                      'tsr_controller': {'autostart'},
                      'tsr_recorder': {'output_dir', 'topics', 'chunk_size'}}
EXPECTED_LIVE = {'tsr_sim': {'progress_every', 'republish_period'},
                 'tsr_controller': {'max_tension', 'law', 'koopman_mpc.horizon', 'mass'},
                 'tsr_recorder': {'flush_period', 'silence_warning'}}


def schema_descriptors(node):
    """{name: (description, read only, integer range, floating-point range)} of what `node`
    declares, as its schema classes (`test_parameter_schemas.node_schemas`) describe it."""
    import dataclasses
    from test_parameter_schemas import node_schemas
    from tsr_sim import ros_io
    from tsr_sim.schema import AT_CONFIGURE, AT_START
    expected = {}
    for section, schema in node_schemas()[node]:
        # The controller reads the law sections and the units at configure.
        applied = AT_CONFIGURE if node == 'tsr_controller' and (
            section or schema.__name__ == 'ScaleSettings') else None
        for field in dataclasses.fields(schema):
            default = 1.0 if field.default is None else field.default  # computed: a float
            read_only = (applied or field.metadata['applied']) == AT_START
            d = ros_io.parameter_descriptor(field.metadata, default, read_only)
            name = f'{section}.{field.name}' if section else field.name
            expected[name] = (d.description, d.read_only, list(d.integer_range),
                              list(d.floating_point_range))
    return expected


def test_every_number_has_a_range(ros, start_node, tmp_path):
    """`ros2 param describe` shows a range for every numeric parameter of the three nodes
    (rclpy's own aside), and read-only for what is not applied live: each parameter as its
    schema class declares it, and no other."""
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import DescribeParameters, ListParameters
    for node in EXECUTABLES:
        params = {'output_dir': str(tmp_path)} if node == 'tsr_recorder' else None
        start_node(*EXECUTABLES[node], node, params)
    numeric = (ParameterType.PARAMETER_INTEGER, ParameterType.PARAMETER_DOUBLE)
    for node in EXECUTABLES:
        names = ros.call(ListParameters, f'{node}/list_parameters',
                         ListParameters.Request(), resend=2.0).result.names
        descriptors = ros.call(DescribeParameters, f'{node}/describe_parameters',
                               DescribeParameters.Request(names=names), resend=2.0).descriptors
        unbounded = [d.name for d in descriptors if d.type in numeric
                     and not (d.integer_range or d.floating_point_range)]
        assert unbounded == [], node
        assert all(d.description for d in descriptors if d.name != 'use_sim_time'
                   and d.name != 'start_type_description_service'), node
        read_only = {d.name for d in descriptors if d.read_only}
        settable = set(names) - read_only
        assert EXPECTED_READ_ONLY[node] <= read_only and EXPECTED_LIVE[node] <= settable, node
        described = {d.name: (d.description, d.read_only, list(d.integer_range),
                              list(d.floating_point_range)) for d in descriptors
                     if d.name not in ('use_sim_time', 'start_type_description_service')}
        assert described == schema_descriptors(node), node


def test_the_config_files_are_keyed_for_any_namespace():
    for path in SHIPPED.values():
        (key,) = yaml.safe_load(pathlib.Path(path).read_text())
        assert key.startswith('/**/'), path
