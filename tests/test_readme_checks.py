"""What a newcomer meets first: the README's commands, paths, start and table agree with what
the scripts and deploy do, and `scripts/setup.sh` refuses an interpreter the wheels do not fit
in one line before it does anything else."""

import ast
import os
import re
import shlex
import subprocess
import sys

import pytest
from tsr_sim import dynamics

from conftest import ROOT

from lab import main_job
from tsr_koopman_ctrl.commands import deploy
from tsr_koopman_ctrl.deployment import COLUMNS, summary_table

README = (ROOT / 'README.md').read_text()
SETUP = ROOT / 'scripts' / 'setup.sh'
#: The Python the wheels are built for, as setup.sh requires it.
REQUIRED_PYTHON = re.search(r'^REQUIRED_PYTHON=(\S+)$', SETUP.read_text(), re.M).group(1)


def code_blocks(language):
    return re.findall(rf'^```{language}\n(.*?)^```', README, re.M | re.S)


# --------------------------------------------------------------------------- Python version

def test_the_readme_names_the_python_version_setup_requires():
    assert REQUIRED_PYTHON == '3.11'
    assert f'Python {REQUIRED_PYTHON}' in README
    assert f'{sys.version_info.major}.{sys.version_info.minor}' == REQUIRED_PYTHON


def fake_python(directory, version):
    """An executable that answers any call with `version`, as `python -c ...` would print it."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / 'python3'
    path.write_text(f'#!/bin/sh\necho {version}\n')
    path.chmod(0o755)
    return path


def run_setup(tmp_path, version, venv_version=None, sourced=False):
    """setup.sh copied into an empty repository, `python3` on PATH answering `version` (and a
    venv whose python answers `venv_version`, if given): (exit status, stderr, the repo)."""
    repo = tmp_path / 'repo'
    (repo / 'scripts').mkdir(parents=True)
    (repo / 'scripts' / 'setup.sh').write_text(SETUP.read_text())
    shims = fake_python(tmp_path / 'bin', version).parent
    if venv_version:
        fake_python(repo / '.venv' / 'bin', venv_version).rename(repo / '.venv/bin/python')
    environment = {k: v for k, v in os.environ.items() if k != 'TSR_PYTHON'}
    environment['PATH'] = f'{shims}:/usr/bin:/bin'
    script = str(repo / 'scripts' / 'setup.sh')
    command = (['bash', '-c', f'source {shlex.quote(script)}; echo "returned $?"'] if sourced
               else ['bash', script])
    done = subprocess.run(command, capture_output=True, text=True, env=environment, timeout=60)
    return done.returncode, done.stderr, done.stdout, repo


def test_setup_refuses_another_python_in_one_line_before_anything_else(tmp_path):
    status, err, _, repo = run_setup(tmp_path, '3.12')
    assert status == 1
    assert err == ('[setup] Python 3.11 is required: python3 is 3.12; install python3.11 and '
                   'run again with TSR_PYTHON=python3.11\n')
    assert sorted(p.name for p in repo.iterdir()) == ['scripts']      # nothing made
    # Sourced (as deploy.sh and test.sh do), it returns 1 and leaves the caller's shell be.
    status, err, out, _ = run_setup(tmp_path / 'sourced', '3.12', sourced=True)
    assert (status, out, len(err.splitlines())) == (0, 'returned 1\n', 1)


def test_setup_refuses_a_venv_made_with_another_python(tmp_path):
    status, err, _, repo = run_setup(tmp_path, '3.11', venv_version='3.12')
    assert status == 1
    assert err == (f'[setup] Python 3.11 is required: {repo}/.venv has Python 3.12; remove it '
                   'and run again with TSR_PYTHON=python3.11\n')


def test_setup_goes_on_with_python_3_11_and_stops_at_a_failed_install(tmp_path):
    """Past the check; the fake interpreter makes no venv, so the install fails: the set-up
    stops there, says so, and stamps nothing as installed."""
    status, err, _, repo = run_setup(tmp_path, '3.11')
    assert 'is required' not in err
    assert (status, err.splitlines()[-1]) == (1, '[setup] set-up failed')
    assert not (repo / '.venv' / '.tsr-installed').exists() and not (repo / 'ros2_ws').exists()


# --------------------------------------------------------------------------- the start

def test_the_readme_s_start_is_deploy_s_default_in_its_layout(capsys):
    """--x0 takes the state [theta, theta', l - 1, l']: the README gives the paper's start in
    that layout, as deploy's help does."""
    match = re.search(r'`--x0 ([-\d. ]+)`', README)
    assert match, 'the README gives no --x0'
    start = [float(v) for v in match.group(1).split()]
    assert start == dynamics.PAPER_INITIAL_STATE.tolist()
    assert "theta, theta', l - 1, l'" in README
    with pytest.raises(SystemExit):
        deploy.parse_args(['--help'])
    shown = ' '.join(capsys.readouterr().out.split())
    assert 'the third value is l - 1, not l' in shown and match.group(1) in shown


# --------------------------------------------------------------------------- paths

#: Paths the README's code writes itself, other than with `--out`.
MADE_BY_THE_README = {'models/retrained': "the retrain call's output"}
PATH_LIKE = re.compile(r'/|\.(md|py|sh|yaml|yml|json|png|mcap|parquet)$')


def paths_in_code():
    """(paths, outputs) of the README's bash and python blocks: every token or string that
    names a file or folder, and the folders the commands write (`--out DIR`)."""
    paths, outputs = [], set(MADE_BY_THE_README)
    for block in code_blocks('bash'):
        for line in block.replace('\\\n', ' ').splitlines():
            tokens = shlex.split(line, comments=True)
            paths += [t for t in tokens if PATH_LIKE.search(t) and not t.startswith('-')]
            outputs |= {after for before, after in zip(tokens, tokens[1:]) if before == '--out'}
    for block in code_blocks('python'):
        paths += [node.value for node in ast.walk(ast.parse(block))
                  if isinstance(node, ast.Constant) and isinstance(node.value, str)
                  and PATH_LIKE.search(node.value)]
    return paths, outputs


def test_every_path_in_the_readme_s_code_exists_is_made_by_it_or_is_a_placeholder():
    paths, outputs = paths_in_code()
    assert {'scripts/deploy.sh', 'bags/', 'models/retrained'} <= set(paths)   # the blocks read
    missing = [path for path in paths
               if not (re.search(r'<[^>]+>', path) or '://' in path or path in outputs
                       or (ROOT / path).exists())]
    assert not missing, f'paths in the README\'s code that nothing makes: {missing}'


# --------------------------------------------------------------------------- the table

def readme_table():
    """(headers, rows of cells) of the README's main-job table."""
    section = README.split('<!-- main_job:begin -->')[1].split('<!-- main_job:end -->')[0]
    lines = [line for line in section.splitlines() if line.startswith('|')]
    cells = [[cell.strip() for cell in line.strip('|').split('|')] for line in lines]
    return cells[0], cells[2:]


def test_the_readme_s_table_has_deploy_s_names_units_and_cells():
    headers, rows = readme_table()
    assert tuple(headers) == main_job.HEADLINE_COLUMNS
    assert set(headers) <= set(COLUMNS), 'a README column deploy does not print'
    assert rows and all(len(row) == len(headers) for row in rows)
    row = {'controller': 'koopman_lqr', 'x0': [0.0, 0.0, -0.99, 0.5], 'settle_tau': 5.07,
           'halted': False, 'halt_tau': None, 'steps': 2000, 'planned_steps': 2000,
           'final_state': [0.0, 0.0, 0.0, 0.0], 'swing': 0.6921, 'theta_min': -0.6921,
           'theta_max': 0.2, 'length_overshoot': 0.0092, 'tension_max': 4.61,
           'tension_integral': 50.0, 'compute_median_us': 1520.0, 'compute_p99_us': 5200.0,
           'frontier_tau': 3.83, 'frontier_ratio': 1.3238}
    deployed = summary_table([row]).splitlines()
    printed = dict(zip(deployed[0].strip('| ').split(' | '), deployed[2].strip('| ').split(' | ')))
    shown = main_job.headline([row]).splitlines()[-3].strip('| ').split(' | ')
    for header, cell in zip(headers, shown):
        cell = cell.replace('**', '')
        if header == 'law':
            assert cell.startswith(f"`{row['controller']}`")
        else:
            assert cell == printed[header], header
    # The README's figures are written as deploy prints them: ms and rad, overshoot in %.
    for readme_row in rows:
        cells = dict(zip(headers, readme_row))
        assert re.fullmatch(r'\d+(\.\d+)? / \d+(\.\d+)?', cells['compute median / p99 [ms]'])
        assert re.fullmatch(r'\d\.\d{3}', cells['swing [rad]'])
        assert re.fullmatch(r'\d+\.\d{2}%', cells['l overshoot'])
