"""ROS 2 parameter files (the YAML `--params-file` takes) read without ROS: the one node
section's ros__parameters, or one error line naming the file."""

import re


def _load(path, compose=False):
    """The YAML documents of `path`, as values or (`compose`) as node trees, which keep the
    quoting rcl types by (ValueError '<path>: why' if it cannot be read as YAML)."""
    import yaml
    try:
        with open(path) as stream:
            return list(yaml.compose_all(stream) if compose else yaml.safe_load_all(stream))
    except OSError as error:
        raise ValueError(f'{path}: {error.strerror}') from None
    except UnicodeDecodeError:
        raise ValueError(f'{path}: not a text file') from None
    except yaml.YAMLError as error:
        mark = getattr(error, 'problem_mark', None)
        where = f' (line {mark.line + 1})' if mark is not None else ''
        raise ValueError(f'{path}: not valid YAML{where}') from None


def node_parameters(path):
    """{name: value} of the file's one `<node>: ros__parameters:` section (ValueError if the
    file is not such a file)."""
    documents = _load(path)
    try:
        (document,) = documents
        (section,) = document.values()
        parameters = section['ros__parameters']
        if not isinstance(parameters, dict):
            raise TypeError(parameters)
    except (ValueError, KeyError, TypeError, AttributeError):
        raise ValueError(f'{path}: not a parameter file with one node section '
                         '(<node>: ros__parameters: ...)') from None
    return dict(parameters)


#: How rcl's YAML parser types a plain (unquoted) scalar in a list, as far as we follow it;
#: anything else (hex, null, ...) is left to rcl.
_BOOLS = {'true', 'True', 'TRUE', 'yes', 'Yes', 'YES', 'on', 'On', 'ON',
          'false', 'False', 'FALSE', 'no', 'No', 'NO', 'off', 'Off', 'OFF'}
_INTEGER = re.compile(r'[-+]?[0-9]+')
_DOUBLE = re.compile(r'[-+]?([0-9]+\.[0-9]*|\.[0-9]+|[0-9]+)([eE][-+]?[0-9]+)?'
                     r'|[-+]?\.(inf|Inf|INF)|\.(nan|NaN|NAN)')
_WORD = re.compile(r'[A-Za-z_][A-Za-z0-9_/]*')


def _scalar_type(node):
    """'bool', 'integer', 'double' or 'string' as rcl would read this list element, or None
    where we do not follow rcl that far."""
    import yaml
    if not isinstance(node, yaml.ScalarNode):
        return None
    if node.style:                         # quoted
        return 'string'
    text = node.value
    if text in _BOOLS:
        return 'bool'
    if _INTEGER.fullmatch(text):
        return 'integer'
    if _DOUBLE.fullmatch(text):
        return 'double'
    return 'string' if _WORD.fullmatch(text) and text.lower() not in ('null', '~') else None


def _structure_problem(node, where=()):
    """What rcl would refuse in a composed YAML document (None if nothing we check): a value
    outside a `ros__parameters` mapping, or a list whose elements differ in type."""
    import yaml
    name = '.'.join(where)
    if 'ros__parameters' in where:
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                problem = _structure_problem(value, where + (key.value,))
                if problem:
                    return problem
        elif isinstance(node, yaml.SequenceNode):
            types = [_scalar_type(element) for element in node.value]
            if None not in types and len(set(types)) > 1:
                parameter = '.'.join(where[where.index('ros__parameters') + 1:])
                return (f"parameter '{parameter}' mixes {' and '.join(sorted(set(types)))} "
                        'in one list (a ROS parameter array has one type)')
        return None
    if isinstance(node, yaml.ScalarNode) and node.value in ('', '~', 'null'):
        return f"'{name}' is empty (<node>: ros__parameters: ...)"
    if not isinstance(node, yaml.MappingNode):
        return (f"'{name}' has a value outside ros__parameters "
                '(<node>: ros__parameters: ...)')
    for key, value in node.value:
        if key.value == 'ros__parameters' and not isinstance(value, yaml.MappingNode):
            return (f"'{name}.ros__parameters' is not a mapping "
                    '(<node>: ros__parameters: {name: value, ...})')
        problem = _structure_problem(value, where + (key.value,))
        if problem:
            return problem
    return None


def params_file_problem(argv):
    """Why the first `--params-file` in a `--ros-args` section of `argv` cannot be read as a
    parameter file (None if it can, empty ones included, as rcl takes them): not YAML, not
    mappings, a value outside `ros__parameters` or a list of mixed types; rcl checks the rest.
    A node says it before `rclpy.init`, whose own [ERROR] line would come first."""
    inside = False
    for index, token in enumerate(argv):
        if token == '--ros-args':
            inside = True
        elif token == '--':
            inside = False
        elif inside and token == '--params-file' and index + 1 < len(argv):
            path = argv[index + 1]
            try:
                documents = _load(path)
            except ValueError as error:
                return f'--params-file {error}'
            if not all(document is None or isinstance(document, dict)
                       for document in documents):
                return f'--params-file {path}: not a parameter file (<node>: ros__parameters: ...)'
            # Read again as node trees (a valid file by now): rcl types list elements by their
            # quoting, which the values above have lost.
            for document in _load(path, compose=True):
                problem = document is not None and _structure_problem(document)
                if problem:
                    return f'--params-file {path}: {problem}'
    return None
