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


#: (file content, what we say before rcl starts): each a mistake rcl refuses too, in its own
#: words after an [ERROR] line, or a file it takes.
STRUCTURE_CASES = [
    ('a: 1\n', "'a' has a value outside ros__parameters"),
    ('a:\n  x: 1\n', "'a.x' has a value outside ros__parameters"),
    ('a:\n  ros__parameters: {x: 1}\n  y: 2\n', "'a.y' has a value outside ros__parameters"),
    ('a: [1]\n', "'a' has a value outside ros__parameters"),
    ('a:\n', "'a' is empty"),
    ('a:\n  ros__parameters:\n', "'a.ros__parameters' is not a mapping"),
    ('/**:\n  ros__parameters: 5\n', "'/**.ros__parameters' is not a mapping"),
    ('/**:\n  ros__parameters:\n    q: [1, 2.5]\n',
     "parameter 'q' mixes double and integer in one list"),
    ('/**:\n  ros__parameters:\n    q: [-1.5, 3]\n',
     "parameter 'q' mixes double and integer in one list"),
    ('/**:\n  ros__parameters:\n    g:\n      q: [true, 1]\n',
     "parameter 'g.q' mixes bool and integer in one list"),
    ('/**:\n  ros__parameters:\n    q: ["1", 2]\n',
     "parameter 'q' mixes integer and string in one list"),
    ('/**:\n  ros__parameters:\n    q: [a, 1]\n',
     "parameter 'q' mixes integer and string in one list"),
    ('/**:\n  ros__parameters:\n    q: [1e3, 2.0, .inf, 1.]\n', None),
    ('/**:\n  ros__parameters:\n    q: [yes, off, True]\n', None),
    ("/**:\n  ros__parameters:\n    q: ['a', b, c_1]\n", None),
    ('/**:\n  ros__parameters:\n    q: []\n    r: [+1, 2]\n', None),
    ('a:\n  ros__parameters: {}\n', None),
    ('ns:\n  a:\n    ros__parameters: {x: 1}\nb:\n  ros__parameters: {y: 2}\n', None)]


@pytest.mark.parametrize('content, problem', STRUCTURE_CASES)
def test_a_value_outside_ros_parameters_or_a_mixed_list_is_said_in_one_line(
        tmp_path, content, problem):
    path = tmp_path / 'params.yaml'
    write(path, content)
    found = params_file_problem(['sim_node', '--ros-args', '--params-file', str(path)])
    if problem is None:
        assert found is None
    else:
        assert found.startswith(f'--params-file {path}: {problem}') and '\n' not in found


@pytest.mark.ros
def test_rcl_refuses_what_we_refuse_and_takes_what_we_take(tmp_path):
    """rcl's own parser, the independent reference: each file we refuse it refuses, each we
    pass it takes."""
    import rclpy
    from rclpy.context import Context
    from rclpy.impl.implementation_singleton import rclpy_implementation
    verdicts = []
    for index, (content, problem) in enumerate(STRUCTURE_CASES):
        path = tmp_path / f'params{index}.yaml'
        write(path, content)
        context = Context()
        try:
            rclpy.init(args=['node', '--ros-args', '--params-file', str(path)], context=context)
            taken = True
            rclpy.shutdown(context=context)
        except rclpy_implementation.RCLError:
            taken = False
        verdicts.append((content, taken))
    assert verdicts == [(content, problem is None) for content, problem in STRUCTURE_CASES]
