"""The house's floors: no import runs back up a floor, the product never imports the lab, and
the lab stands on the public API, never on the commands.

Floors, from the ground: the plant core (tsr_sim, ROS-free); the model and the bags; the laws;
the figures of a run; learning; campaigns (ROS-free: runs on Dask, rows, reports); the ROS
glue and the process layer (nodes, the deployment, the launcher, tsr_sim's node and ros_io);
the commands, the tools' argparse types and the test fixtures; the lab beside it all.
A module imports from its own floor or below. Read from the source (ast), imports inside
functions included.
"""

import ast

import pytest

from conftest import ROOT

SOURCES = {'tsr_sim': ROOT / 'ros2_ws/src/tsr_sim/tsr_sim',
           'tsr_koopman_ctrl': ROOT / 'ros2_ws/src/tsr_koopman_ctrl/tsr_koopman_ctrl',
           'lab': ROOT / 'lab'}
FLOORS = [
    ('tsr_sim.dynamics', 'tsr_sim.units', 'tsr_sim.plant', 'tsr_sim.variants', 'tsr_sim.wire',
     'tsr_sim.parameter_file', 'tsr_sim.share', 'tsr_sim'),
    ('tsr_koopman_ctrl.model', 'tsr_koopman_ctrl.bag'),
    ('tsr_koopman_ctrl.control',),
    ('tsr_koopman_ctrl.evaluation',),
    ('tsr_koopman_ctrl.learning',),
    ('tsr_koopman_ctrl.campaign',),
    ('tsr_koopman_ctrl.nodes', 'tsr_koopman_ctrl.deployment', 'tsr_koopman_ctrl.launcher',
     'tsr_sim.sim_node', 'tsr_sim.ros_io'),
    ('tsr_koopman_ctrl.commands', 'tsr_koopman_ctrl.testing', 'tsr_koopman_ctrl.arguments',
     'tsr_koopman_ctrl'),
    ('lab',),
]


def floor(module):
    """The floor of a project module (the longest matching room), or None (not ours)."""
    best = None
    for index, rooms in enumerate(FLOORS):
        for room in rooms:
            if module == room or module.startswith(room + '.'):
                if best is None or len(room) > best[1]:
                    best = (index, len(room))
    return None if best is None else best[0]


def modules():
    for package, directory in SOURCES.items():
        for path in sorted(directory.rglob('*.py')):
            parts = path.relative_to(directory).with_suffix('').parts
            name = '.'.join((package, *parts))
            yield (name[:-len('.__init__')] if name.endswith('.__init__') else name), path


def import_statements(path, name):
    """(module, [names]) of each import in `path` (names: those of a `from module import`)."""
    tree = ast.parse(path.read_text())
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from ((alias.name, []) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit('.', node.level - 1)[0] if node.level > 1 else package
                module = f'{base}.{node.module}' if node.module else base
            else:
                module = node.module
            yield module, [alias.name for alias in node.names]


def imports(path, name, names=False):
    """The modules `path` imports; `names`: also `module.name` for each name of a
    `from module import name` (a submodule imported so)."""
    for module, imported in import_statements(path, name):
        yield module
        if names:
            yield from (f'{module}.{alias}' for alias in imported)


@pytest.mark.parametrize('name, path', list(modules()), ids=lambda v: str(v))
def test_no_import_runs_back_up_a_floor(name, path):
    own = floor(name)
    assert own is not None, f'{name} has no floor: add it to FLOORS'
    upward = [target for target in imports(path, name)
              if (floor(target) or 0) > own]
    assert upward == [], f'{name} (floor {own}) imports from above: {upward}'


def test_the_laws_never_import_the_figures_and_the_product_never_the_lab():
    for name, path in modules():
        targets = set(imports(path, name))
        if name.startswith('tsr_koopman_ctrl.control'):
            assert not any(t.startswith('tsr_koopman_ctrl.evaluation') for t in targets), name
        if not name.startswith('lab'):
            assert not any(t == 'lab' or t.startswith('lab.') for t in targets), name


def test_the_lab_never_imports_the_commands():
    """The commands are parse -> call -> print over the public API; the lab calls that API
    (learning.data, bag.files, control.registry.parse_assignments, arguments), not a command's
    main or its internals."""
    found = [(name, target) for name, path in modules() if name.startswith('lab')
             for target in imports(path, name, names=True)
             if target == 'tsr_koopman_ctrl.commands'
             or target.startswith('tsr_koopman_ctrl.commands.')]
    assert found == []


CONTROL = 'tsr_koopman_ctrl.control'


def control_imports(name, path, submodules):
    """The control modules `name` imports, inside functions too: each submodule, and the
    package itself for a name its __init__ gives (`from tsr_koopman_ctrl.control import
    CONTROLLERS`)."""
    found = set()
    for module, imported in import_statements(path, name):
        if module in submodules:
            found.add(module)
        elif module == CONTROL:
            given = {f'{module}.{alias}' for alias in imported}
            found |= given & submodules
            if given - submodules:
                found.add(CONTROL)
    return found - {name}


def control_graph():
    """{control module: the control modules it imports}, the package's __init__ included."""
    control = {name: path for name, path in modules()
               if name == CONTROL or name.startswith(CONTROL + '.')}
    submodules = set(control) - {CONTROL}
    return {name: control_imports(name, path, submodules) for name, path in control.items()}


def test_the_laws_settings_import_nothing_of_control():
    """Every law imports control/settings.py: it stands on tsr_sim's schema alone, imports
    inside functions included (a lazy one closed a circle through the registry)."""
    graph = control_graph()
    assert graph[f'{CONTROL}.settings'] == set()


def test_no_import_cycle_among_the_control_modules():
    graph = control_graph()
    cycles, state = [], {}

    def visit(module, path):
        state[module] = 'open'
        for target in sorted(graph.get(module, ())):
            if state.get(target) == 'open':
                cycles.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target, path + [target])
        state[module] = 'done'
    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert cycles == [], 'import cycles in control/: ' + '; '.join(
        ' -> '.join(m.rpartition('.')[2] or m for m in cycle) for cycle in cycles)


def test_one_did_you_mean():
    """Every refusal of an unknown name hints alike: one function (`tsr_sim.schema.did_you_mean`)
    and no other caller of difflib."""
    callers = {name for name, path in modules() if 'difflib' in imports(path, name)}
    assert callers == {'tsr_sim.schema'}
