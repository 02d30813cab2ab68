"""Parameter files read without ROS: the node section's parameters, or one line."""

import pytest

from tsr_sim.parameter_file import node_parameters, params_file_problem


def write(path, content):
    """Bytes or text at `path`; None: leave it missing."""
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)


def test_the_one_node_section_s_parameters(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    mode: lockstep\n    rate_hz: 50.0\n')
    assert node_parameters(path) == {'mode': 'lockstep', 'rate_hz': 50.0}


@pytest.mark.parametrize('content, message', [
    ('a: [\n', 'not valid YAML (line 2)'),
    ('', 'not a parameter file with one node section'),
    ('- 1\n', 'not a parameter file with one node section'),
    ('node:\n  mode: lockstep\n', 'not a parameter file with one node section'),
    ('a:\n  ros__parameters: {}\nb:\n  ros__parameters: {}\n', 'one node section'),
    ('node:\n  ros__parameters: [1]\n', 'not a parameter file with one node section'),
    (b'\xff\xfe\x00binary', 'not a text file'),
    (None, 'No such file or directory')])
def test_anything_else_is_one_line_naming_the_file(tmp_path, content, message):
    path = tmp_path / 'p.yaml'
    write(path, content)
    with pytest.raises(ValueError) as error:
        node_parameters(path)
    assert str(error.value).startswith(f'{path}: ') and message in str(error.value)
    assert '\n' not in str(error.value)


@pytest.mark.parametrize('content, problem', [
    (None, 'No such file or directory'), ('a: [\n', 'not valid YAML (line 2)'),
    (b'\xff\xfe', 'not a text file'),
    ('[1]\n', 'not a parameter file (<node>: ros__parameters: ...)'),
    ('/**:\n  ros__parameters: {mode: timed}\n', None),
    ('', None), ('# nothing yet\n', None),      # rcl starts with these, so must we
    ('a:\n  ros__parameters: {x: 1}\n---\nb:\n  ros__parameters: {y: 2}\n', None)])
def test_a_params_file_is_checked_before_rcl_logs_its_own_error(tmp_path, content, problem):
    path = tmp_path / 'params.yaml'
    write(path, content)
    found = params_file_problem(['sim_node', '--ros-args', '--params-file', str(path)])
    assert found == (problem and f'--params-file {path}: {problem}')


def test_only_a_params_file_rcl_reads_is_checked(tmp_path):
    """rcl reads --params-file inside a --ros-args section only (up to `--`)."""
    missing = str(tmp_path / 'missing.yaml')
    for argv in (['node', '--params-file', missing],
                 ['node', '--ros-args', '-p', 'a:=1', '--', '--params-file', missing],
                 ['node', '--ros-args', '--params-file']):
        assert params_file_problem(argv) is None
    assert params_file_problem(['node', '--ros-args', '-r', '__ns:=/a', '--params-file',
                                missing, '--']).endswith('No such file or directory')
