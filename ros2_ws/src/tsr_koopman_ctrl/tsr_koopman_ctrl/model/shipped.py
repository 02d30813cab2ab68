"""Where models are found: a directory given by path, or a model shipped with the package.

The shipped models are installed to ``share/tsr_koopman_ctrl/models/<name>`` (setup.py's
data_files) and found through the ament index, so a node started from any directory (as
``ros2 run`` users do) loads them by name.
"""

import os

from tsr_sim.share import NOT_SOURCED, share_directory

PACKAGE = 'tsr_koopman_ctrl'
#: The paper's model with its errors fixed: what the prediction studies and the benchmarks load
#: unless told otherwise. Each law names its own model in its settings (models/README.md).
DEFAULT_MODEL = 'koopman_default'


def installed_models_dir():
    """share/tsr_koopman_ctrl/models of the sourced workspace, or None if it is not found."""
    share = share_directory(PACKAGE)
    return None if share is None else os.path.join(share, 'models')


def resolve(model):
    """The directory of `model`: an existing directory as given, else a shipped model's name.

    Raises ValueError naming every path tried.
    """
    model = os.fspath(model)
    tried = [os.path.abspath(model)]
    if os.path.isdir(model):
        return model
    shipped = installed_models_dir()
    if shipped is not None and not os.path.isabs(model):
        candidate = os.path.join(shipped, model)
        if os.path.isdir(candidate):
            return candidate
        tried.append(candidate)
        names = sorted(n for n in os.listdir(shipped) if os.path.isdir(os.path.join(shipped, n)))
        tried.append(f'the shipped models are {", ".join(names)}')
    elif shipped is None:
        tried.append(f'share/{PACKAGE}/models ({NOT_SOURCED})')
    from tsr_koopman_ctrl.model.model_file import ModelFileError
    raise ModelFileError(f'{model}: no such model directory (tried {", ".join(tried)})')
