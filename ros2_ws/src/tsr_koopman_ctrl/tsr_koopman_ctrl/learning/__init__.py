"""Learning the lifted model: data, the deep Koopman model and its training, the baselines and
the prediction error they are all judged by.

    from tsr_koopman_ctrl.learning import Edmd, Sindy, multistep_errors, sample, SamplingConfig
    data, dropped = sample(SamplingConfig(trajectories=4000))
    edmd = Edmd(lift_dim=36, stabilise=True).fit(data)
    errors = multistep_errors(edmd.predict(data.x[:, 0], data.u), data.x)

Importing this package does not import torch; the deep model and the trainer do
(`learning.deep_koopman`, `learning.trainer`).
"""

from tsr_koopman_ctrl.learning.baselines import Edmd, Sindy  # noqa: F401
from tsr_koopman_ctrl.learning.dataset import (  # noqa: F401
    concatenate, Dataset, from_loop, sample, SamplingConfig)
from tsr_koopman_ctrl.learning.errors import multistep_errors  # noqa: F401
