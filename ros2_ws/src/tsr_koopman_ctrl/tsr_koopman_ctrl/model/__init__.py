"""The learned model as the controller uses it: the model file and the lifted system in numpy.

    from tsr_koopman_ctrl.model import LiftedModel
    model = LiftedModel.load('koopman_default')        # a shipped name or a directory
    states = model.predict(x0, u)                      # (N, n), (N, T) -> (N, T + 1, n)

No torch here: the controller's hot path is numpy; training lives in `tsr_koopman_ctrl.learning`.
"""

from tsr_koopman_ctrl.model.lifted import (controllability_rank, LiftedModel)  # noqa: F401
from tsr_koopman_ctrl.model.model_file import (KoopmanConfig, ModelConfig,  # noqa: F401
                                               ModelFileError, TrainingConfig)
from tsr_koopman_ctrl.model.shipped import DEFAULT_MODEL, resolve  # noqa: F401
