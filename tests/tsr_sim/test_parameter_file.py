"""Parameter files read without ROS: the node section's parameters, or one line."""

import pytest

from tsr_sim.parameter_file import node_parameters


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
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    with pytest.raises(ValueError) as error:
        node_parameters(path)
    assert str(error.value).startswith(f'{path}: ') and message in str(error.value)
    assert '\n' not in str(error.value)
