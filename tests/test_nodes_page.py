"""docs/nodes.md against the code, ROS-free: every parameter table lists exactly the parameters
its node declares, with the defaults the code declares, and the controller's diagnostics keys
are the ones its `diagnose` and the default law's `diagnostics()` report.

The nodes import rclpy and the built messages; what they declare is in their schema classes
(`tsr_sim.schema`), which are ROS-free: `tsr_sim.plant`, `tsr_sim.node_parameters`,
`nodes.controller_parameters`, `nodes.recorder_parameters`."""

import ast
import math
import re

from conftest import ROOT
import pytest
from tsr_sim.schema import fields

PAGE = (ROOT / 'docs' / 'nodes.md').read_text()
SIM = ROOT / 'ros2_ws' / 'src' / 'tsr_sim' / 'tsr_sim'
CTRL = ROOT / 'ros2_ws' / 'src' / 'tsr_koopman_ctrl' / 'tsr_koopman_ctrl'
#: Declared by `ros_io.run_node` for every node (`pin_threads`, `raise_priority`).
EVERY_NODE = ('threads', 'thread_priority')
#: The settings sections the controller declares as `<section>.<setting>`; on the page
#: `<law>.<setting>` stands for every law's.
LAW_SECTION = '<law>.<setting>'


# -- the page --------------------------------------------------------------------------------

def table_after(marker):
    """The rows (lists of cells) of the first table after the line starting with `marker`."""
    lines = PAGE.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(marker))
    rows = []
    for line in lines[start + 1:]:
        if line.startswith('|'):
            rows.append([cell.strip() for cell in line.strip().strip('|').split(' | ')])
        elif rows:
            break
    return rows[2:]       # past the header and the rule


def documented(marker):
    """{parameter: the page's default for it} of a parameter table: the first cell names one
    parameter or several (`a`, `b` (value)); a value in brackets after a name is its default,
    else the default cell's (split at ', ' when it has one part per name)."""
    names = {}
    for row in table_after(marker):
        cell, default = row[0], row[1]
        found = re.findall(r'`([^`]+)`(?: \(([^)]*)\))?', cell)
        parts = default.split(', ')
        for i, (name, own) in enumerate(found):
            if own:
                names[name] = own
            elif len(found) > 1 and len(parts) == len(found):
                names[name] = parts[i]
            else:
                names[name] = default
    return names


def page_value(text):
    """The number a page's default gives ('13.93 N (u = 5)' -> 13.93, '100 km' -> 1e5,
    '1 MiB' -> 2**20, 'pi/2 rad' -> pi/2, 'u = 3' -> ('u', 3.0)), True/False, a word in
    backquotes, or None where the page describes the default in words ('the paper's')."""
    text = text.strip()
    if text.startswith('`'):
        return text.split('`')[1]
    if text.split(' ')[0] in ('true', 'false'):
        return text.startswith('true')
    if text.startswith('pi/'):
        return math.pi / float(re.match(r'pi/([0-9.]+)', text).group(1))
    match = re.match(r'u = ([-+0-9.e]+)', text)
    if match:
        return ('u', float(match.group(1)))
    match = re.match(r'([-+]?[0-9][0-9.]*(?:e[-+]?[0-9]+)?)(?: (km|MiB))?', text)
    if not match:
        return None
    return float(match.group(1)) * {'km': 1e3, 'MiB': 2 ** 20, None: 1}[match.group(2)]


# -- the code --------------------------------------------------------------------------------

def tree(path):
    return ast.parse(path.read_text())


def module_constants(path):
    """{NAME: value} of a module's top-level `NAME = <literal>` assignments."""
    values = {}
    for node in tree(path).body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and \
                isinstance(node.targets[0], ast.Name):
            try:
                values[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                pass
    return values


def schema_defaults(*schemas):
    """{name: default} of the fields of schema classes (a sequence as a list)."""
    return {name: list(default) if isinstance(default, tuple) else default
            for schema in schemas for name, default, _ in fields(schema)}


def loop_priority(path):
    """The `thread_priority` default a node gets from `run_node(..., priority=...)`."""
    io = module_constants(SIM / 'ros_io.py')
    for node in ast.walk(tree(path)):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == 'run_node':
            keyword = {k.arg: k.value for k in node.keywords}.get('priority')
            return 0 if keyword is None else io[keyword.id]
    raise AssertionError(f'{path.name} has no run_node call')


def computed_defaults():
    """The defaults the simulator computes from the units (a default of None in its schema):
    in newtons at the default units."""
    from tsr_sim import dynamics
    from tsr_sim.units import Scale
    return {'max_tension': Scale().u_to_tension(dynamics.TENSION_LIMIT),
            'safe_tension': Scale().u_to_tension(dynamics.EQUILIBRIUM_TENSION)}


def assert_defaults_agree(table, defaults):
    """Each default the page states as a value equals the code's (the page rounds: 0.1%)."""
    from tsr_sim.units import Scale
    wrong = []
    for name, text in table.items():
        page, code = page_value(text), defaults.get(name)
        if page is None or code in (None, '') or isinstance(code, (list, tuple)):
            continue      # described in words, made at start ('': a new bag's name), a list
        if isinstance(page, tuple):       # 'u = 3': a tension in the paper's units
            page = Scale().u_to_tension(page[1])
        if isinstance(code, bool) or isinstance(page, (bool, str)):
            agree = page == code
        else:
            agree = page == pytest.approx(code, rel=1e-3)
        if not agree:
            wrong.append(f'{name}: page {text!r}, code {code!r}')
    assert not wrong, 'docs/nodes.md gives defaults the code does not: ' + '; '.join(wrong)


# -- the tests -------------------------------------------------------------------------------

def simulator_defaults():
    from tsr_sim import plant, units
    from tsr_sim.node_parameters import ProcessSettings, ScaleSettings, SimulatorNodeSettings
    defaults = schema_defaults(plant.PlantSettings, SimulatorNodeSettings, ScaleSettings,
                               ProcessSettings)
    defaults.update({name: value for name, value in computed_defaults().items()
                     if defaults.get(name, 0) is None})
    defaults.update(thread_priority=loop_priority(SIM / 'sim_node.py'))
    assert (defaults['orbit_rate'], defaults['tether_length'], defaults['mass']) == (
        units.PAPER_ORBIT_RATE, units.PAPER_TETHER_LENGTH, units.DEFAULT_MASS)
    assert set(plant.SCALE_PARAMETERS) == {'orbit_rate', 'tether_length', 'mass'}
    return defaults


def controller_defaults():
    from tsr_koopman_ctrl.nodes.controller_parameters import ControllerNodeSettings
    from tsr_sim import plant
    from tsr_sim.node_parameters import ProcessSettings
    path = CTRL / 'nodes' / 'controller_node.py'
    defaults = schema_defaults(ControllerNodeSettings, ProcessSettings)
    defaults.update({name: None for name in plant.SCALE_PARAMETERS})      # declare_scale
    defaults.update(thread_priority=loop_priority(path))
    return defaults


def test_the_simulator_table_lists_what_the_simulator_declares_with_its_defaults():
    table = documented('**Simulator**')
    defaults = simulator_defaults()
    assert set(table) == set(defaults), (
        f'on the page only: {sorted(set(table) - set(defaults))}; '
        f'declared only: {sorted(set(defaults) - set(table))}')
    assert_defaults_agree(table, defaults)


def test_the_controller_table_lists_what_the_controller_declares_with_its_defaults():
    from tsr_koopman_ctrl.control import registry
    table = documented('**Controller**')
    defaults = controller_defaults()
    sections = {name[:-2] for name in table if name.endswith('.*')}
    assert sections == set(registry.NODE_SECTIONS), sections
    assert LAW_SECTION in table
    plain = {name for name in table if not name.endswith('.*') and name != LAW_SECTION}
    assert plain == set(defaults), (f'on the page only: {sorted(plain - set(defaults))}; '
                                    f'declared only: {sorted(set(defaults) - plain)}')
    assert_defaults_agree({name: table[name] for name in plain}, defaults)


def test_the_page_gives_the_controller_s_default_law():
    from tsr_koopman_ctrl.control import registry
    from tsr_koopman_ctrl.nodes.controller_parameters import ControllerNodeSettings
    assert ControllerNodeSettings().law == registry.DEFAULT_LAW
    assert page_value(documented('**Controller**')['law']) == registry.DEFAULT_LAW


def test_the_recorder_table_lists_what_the_recorder_declares_with_its_defaults():
    path = CTRL / 'nodes' / 'recorder_node.py'
    table = documented('**Recorder**')
    from tsr_koopman_ctrl.nodes.recorder_parameters import RecorderNodeSettings
    defaults = schema_defaults(RecorderNodeSettings)
    assert set(table) == set(defaults), (
        f'on the page only: {sorted(set(table) - set(defaults))}; '
        f'declared only: {sorted(set(defaults) - set(table))}')
    assert_defaults_agree(table, defaults)
    # threads and thread_priority: every node's, in the simulator's table; the recorder's
    # priority default (0) is what the simulator's row says of it.
    assert loop_priority(path) == 0
    row = next(row for row in table_after('**Simulator**') if row[0] == '`thread_priority`')
    assert "the recorder's default 0" in row[2], row


def node_diagnostics_keys():
    """The keys the controller's `diagnose` puts into its values before the law's own: the
    dict it starts from, `values.update(...)` (keywords, `self.<dict>`, a comprehension of
    '<prefix>{k}' over `self.<dict>.items()`) and `values['key'] = ...`."""
    module = tree(CTRL / 'nodes' / 'controller_node.py')
    diagnose = next(node for node in ast.walk(module)
                    if isinstance(node, ast.FunctionDef) and node.name == 'diagnose')

    def attribute_dict_keys(attribute):
        keys = set()
        for node in ast.walk(module):
            if isinstance(node, ast.Assign) and any(
                    isinstance(t, ast.Attribute) and t.attr == attribute for t in node.targets):
                for d in ast.walk(node.value):
                    if isinstance(d, ast.Dict):
                        keys |= {k.value for k in d.keys if isinstance(k, ast.Constant)}
        assert keys, f'self.{attribute}: no dict assigned to it'
        return keys

    keys, law_reported = set(), False
    for node in ast.walk(diagnose):
        if isinstance(node, ast.Assign) and getattr(node.targets[0], 'id', None) == 'values':
            keys |= {k.value for k in node.value.keys}
        elif isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Subscript) and \
                getattr(node.targets[0].value, 'id', None) == 'values':
            keys.add(node.targets[0].slice.value)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and \
                node.func.attr == 'update' and getattr(node.func.value, 'id', None) == 'values':
            keys |= {k.arg for k in node.keywords}
            for arg in node.args:
                if isinstance(arg, ast.Attribute):
                    keys |= attribute_dict_keys(arg.attr)
                elif isinstance(arg, ast.DictComp) and isinstance(arg.key, ast.JoinedStr):
                    prefix = arg.key.values[0].value
                    keys |= {prefix + k for k in
                             attribute_dict_keys(arg.generators[0].iter.func.value.attr)}
                elif isinstance(arg, ast.Call) and arg.func.attr == 'diagnostics':
                    law_reported = True
                else:
                    raise AssertionError(f'diagnose: values.update({ast.unparse(arg)}): a form '
                                         'this test cannot read; teach it')
    assert law_reported, "diagnose no longer reports the law's diagnostics()"
    return keys


def test_the_controller_s_diagnostics_keys_are_the_ones_it_reports():
    """The node's own keys and those of the default law as the node builds it (offset-free,
    under the supervisor), the shipped model given by path."""
    from tsr_koopman_ctrl.control import make_controller, registry
    from tsr_koopman_ctrl.control.supervisor import REASONS
    from tsr_koopman_ctrl.control.nmpc import MODEL
    law = make_controller(registry.DEFAULT_LAW, model=str(ROOT / 'models' / MODEL))
    reported = node_diagnostics_keys() | set(law.diagnostics())
    row = next(row for row in table_after('| node | keys |') if row[0] == 'controller')
    listed = set()
    for key in re.findall(r'`([^`]+)`', row[1]):
        listed |= ({key.replace('<reason>', r) for r in REASONS} if '<reason>' in key
                   else {key})
    assert listed == reported, (f'on the page only: {sorted(listed - reported)}; '
                                f'reported only: {sorted(reported - listed)}')


def test_the_page_value_reader():
    assert page_value('13.93 N (u = 5)') == 13.93
    assert page_value('100 km') == 1e5 and page_value('1 MiB') == 2 ** 20
    assert page_value('pi/2 rad') == math.pi / 2 and page_value('u = 3') == ('u', 3.0)
    assert page_value('`koopman_nmpc`') == 'koopman_nmpc' and page_value('false') is False
    assert page_value("the paper's") is None and page_value('1.1804e-3 rad/s') == 1.1804e-3
