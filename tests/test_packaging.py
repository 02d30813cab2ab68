"""What a user who installs or clones the project relies on: manifests that tell the truth, a
control path without torch, and no reference to files outside the repository."""

import ast
import re
import subprocess
import sys
import xml.etree.ElementTree as ElementTree

import pytest

from conftest import ROOT

SRC = ROOT / 'ros2_ws' / 'src'
#: Import name -> the manifest's name for it (rosdep key or pip package).
DEPENDENCY_NAMES = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm', 'torch': 'python3-torch',
    'mcap': 'mcap', 'mcap_ros2': 'mcap-ros2-support', 'osqp': 'osqp', 'pysindy': 'pysindy',
    'safetensors': 'safetensors', 'daqp': 'daqp', 'optuna': 'optuna', 'casadi': 'casadi',
    'quadprog': 'quadprog', 'clarabel': 'clarabel', 'pytest': 'python3-pytest',
    'threadpoolctl': 'python3-threadpoolctl'}
#: Declared but not imported, and why (the manifest says so too).
NOT_IMPORTED = {'tsr_koopman_ctrl': {'std_msgs', 'rosgraph_msgs', 'zstandard'}}


def imports(package):
    """Top-level names of every module the package's code imports (at any depth)."""
    names = set()
    for path in (SRC / package / package).rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {alias.name.split('.')[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names.add(node.module.split('.')[0])
    return names - set(sys.stdlib_module_names) - {package}


def declared(package):
    """Exec dependencies of package.xml, plus the pip packages its comment names."""
    text = (SRC / package / 'package.xml').read_text()
    root = ElementTree.fromstring(text)
    names = {e.text for e in root.iter('exec_depend')}
    for comment in re.findall(r'<!--\s*pip \(no rosdep key\):(.*?)-->', text, re.S):
        names |= {name.strip() for name in comment.split(',')}
    return names


@pytest.mark.parametrize('package', ['tsr_sim', 'tsr_koopman_ctrl'])
def test_manifest_declares_every_import_and_nothing_stale(package):
    used = {DEPENDENCY_NAMES.get(name, name) for name in imports(package)}
    manifest = declared(package)
    assert used - manifest == set(), f'{package}: imported but not in package.xml'
    stale = manifest - used - NOT_IMPORTED.get(package, set())
    assert stale == set(), f'{package}: in package.xml but never imported'


def test_the_control_path_never_imports_torch_and_casadi_only_for_the_exact_equations():
    """The controller node's imports and a step of the learned laws on their shipped models (the
    main job's koopman_nmpc among them): no torch (training only). Casadi is loaded with the
    exact equations' map only (physics_nmpc, the supervisor's fallback, a cold start's guide,
    the safety filter's backups), never by the registry, the node or a law without them."""
    code = ('import sys\n'
            'import tsr_koopman_ctrl.nodes.controller_node\n'
            'from tsr_koopman_ctrl.control import make_controller\n'
            'from tsr_koopman_ctrl.learning import Edmd, Sindy, multistep_errors\n'
            'make_controller("linear_lqr").compute([0.0, 0.0, -0.99, 0.5])\n'
            'make_controller("koopman_lqr", supervisor="none", safety="none").compute('
            '[0.0, 0.0, -0.99, 0.5])\n'
            'assert "casadi" not in sys.modules, "casadi imported"\n'
            'for name in ("koopman_mpc", "koopman_lqr", "koopman_nmpc"):\n'
            '    make_controller(name).compute([0.0, 0.0, -0.99, 0.5])\n'
            'assert "torch" not in sys.modules, "torch imported"\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_nothing_refers_to_files_outside_the_repository():
    tracked = subprocess.run(['git', 'ls-files'], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.split()
    outside = '../' + 'shared'   # split so this file does not find itself
    offenders = [name for name in tracked if (ROOT / name).is_file()
                 and not (ROOT / name).is_symlink()
                 and outside in (ROOT / name).read_text(errors='ignore')]
    assert offenders == []


def test_lookups_by_name_without_a_sourced_workspace_say_so_in_one_line(monkeypatch):
    """Presets, plant variants and shipped models are found by name through the ament index;
    with AMENT_PREFIX_PATH unset (a bare Python session) each says what is missing, not
    ament_index's OSError."""
    from tsr_koopman_ctrl.control.registry import preset
    from tsr_koopman_ctrl.model.lifted import LiftedModel
    from tsr_koopman_ctrl.model.model_file import ModelFileError
    from tsr_sim.plant import plant_file
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    sourced = 'is the workspace sourced?'
    with pytest.raises(ValueError, match=f"no settings preset 'tuned_settle'.*{sourced}"):
        preset('tuned_settle')
    with pytest.raises(ValueError, match=f"no plant variant 'nominal'.*{sourced}"):
        plant_file('nominal')
    with pytest.raises(ModelFileError, match=f'koopman_default: no such model.*{sourced}'):
        LiftedModel.load('koopman_default')
    # By path they need no workspace.
    config = SRC / 'tsr_koopman_ctrl' / 'config'
    assert preset(str(config / 'tuned_settle.yaml'))['koopman_mpc']['horizon'] == 3
