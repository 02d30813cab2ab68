"""ROS 2 parameter files (the YAML `--params-file` takes) read without ROS: the one node
section's ros__parameters, or one error line naming the file."""


def node_parameters(path):
    """{name: value} of the file's one `<node>: ros__parameters:` section (ValueError if the
    file is not such a file)."""
    import yaml
    try:
        with open(path) as stream:
            document = yaml.safe_load(stream)
    except OSError as error:
        raise ValueError(f'{path}: {error.strerror}') from None
    except UnicodeDecodeError:
        raise ValueError(f'{path}: not a text file') from None
    except yaml.YAMLError as error:
        mark = getattr(error, 'problem_mark', None)
        where = f' (line {mark.line + 1})' if mark is not None else ''
        raise ValueError(f'{path}: not valid YAML{where}') from None
    try:
        (section,) = document.values()
        parameters = section['ros__parameters']
        if not isinstance(parameters, dict):
            raise TypeError(parameters)
    except (ValueError, KeyError, TypeError, AttributeError):
        raise ValueError(f'{path}: not a parameter file with one node section '
                         '(<node>: ros__parameters: ...)') from None
    return dict(parameters)
