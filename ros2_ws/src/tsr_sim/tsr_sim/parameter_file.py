"""ROS 2 parameter files (the YAML `--params-file` takes) read without ROS: the one node
section's ros__parameters, or one error line naming the file."""


def _load(path):
    """The YAML documents of `path` (ValueError '<path>: why' if it cannot be read as YAML)."""
    import yaml
    try:
        with open(path) as stream:
            return list(yaml.safe_load_all(stream))
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


def params_file_problem(argv):
    """Why the first `--params-file` in a `--ros-args` section of `argv` cannot be read as
    YAML mappings (None if each can, empty ones included, as rcl takes them); rcl checks the
    rest. A node says it before `rclpy.init`, whose own [ERROR] line would come first."""
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
    return None
