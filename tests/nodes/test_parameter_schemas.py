"""The nodes' parameters, ROS-free: each node declares them from schema classes
(`tsr_sim.schema`), with a description for every one and a range for every number;
test_parameters.py checks the running nodes against `node_schemas`."""

import ast
import dataclasses

from conftest import ROOT

SIM = ROOT / 'ros2_ws/src/tsr_sim/tsr_sim'
NODES = ROOT / 'ros2_ws/src/tsr_koopman_ctrl/tsr_koopman_ctrl/nodes'


def node_schemas():
    """{node: [(section, schema class)]}: what each node declares, its rclpy ones aside."""
    from tsr_koopman_ctrl.control.registry import settings_sections
    from tsr_koopman_ctrl.nodes.controller_parameters import ControllerNodeSettings
    from tsr_koopman_ctrl.nodes.recorder_parameters import RecorderNodeSettings
    from tsr_sim.node_parameters import ProcessSettings, ScaleSettings, SimulatorNodeSettings
    from tsr_sim.plant import PlantSettings
    return {'tsr_sim': [('', ScaleSettings), ('', PlantSettings), ('', SimulatorNodeSettings),
                        ('', ProcessSettings)],
            'tsr_controller': [('', ControllerNodeSettings), ('', ScaleSettings),
                               ('', ProcessSettings), *settings_sections().items()],
            'tsr_recorder': [('', RecorderNodeSettings), ('', ProcessSettings)]}


def test_every_node_parameter_has_a_description_and_every_number_a_range():
    """What `ros2 param describe` shows comes from the schema: a description for every
    parameter, a range for every number (a side left open: the largest a descriptor holds)."""
    for node, schemas in node_schemas().items():
        for section, schema in schemas:
            for field in dataclasses.fields(schema):
                name, meta = f'{section}.{field.name}'.lstrip('.'), field.metadata
                assert meta['description'], (node, name)
                number = (field.default is None or isinstance(field.default, (int, float))
                          and not isinstance(field.default, bool))
                if number:
                    assert meta['low'] is not None or meta['high'] is not None, (node, name)


def test_the_nodes_declare_their_parameters_from_schema_classes_only():
    """No parameter is declared inline: the nodes call `ros_io.declare_schema` (or
    `declare_scale`) with a schema class, never rclpy's `declare_parameter(s)` or a `declare`
    of their own, and only `declare_schema` calls `declare_parameter`."""
    def calls(path):
        tree = ast.parse(path.read_text())
        for function in [tree, *(node for node in ast.walk(tree)
                                 if isinstance(node, ast.FunctionDef))]:
            for node in ast.walk(function):
                if isinstance(node, ast.Call):
                    func = node.func
                    yield (getattr(function, 'name', None),
                           getattr(func, 'id', None) or getattr(func, 'attr', None))
    for path in (SIM / 'sim_node.py', NODES / 'controller_node.py', NODES / 'recorder_node.py'):
        found = {called for _, called in calls(path)}
        assert not found & {'declare', 'declare_parameter', 'declare_parameters'}, path
        assert 'declare_schema' in found, path
    callers = {function for function, called in calls(SIM / 'ros_io.py')
               if called == 'declare_parameter'} - {None}
    assert callers == {'declare_schema'}
