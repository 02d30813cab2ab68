"""Multi-step prediction error, the one metric every model is judged by (paper Section IV-C).

A model predicts states (N, T + 1, n) from the true x_0 and the recorded tensions; the error is
the squared difference to the true states, averaged over trajectories (and components), per step
and summed over the T steps. Units: the paper's dimensionless state.
"""

import numpy as np
from tsr_sim import dynamics


def multistep_errors(predicted, truth):
    """{'summed_mse', 'final_mse', 'mse_per_step' (T+1), 'summed_mse_per_component' (name ->)}.

    A prediction that blows up counts as such: non-finite values give an infinite error.
    """
    predicted, truth = np.asarray(predicted, dtype=float), np.asarray(truth, dtype=float)
    if predicted.shape != truth.shape:
        raise ValueError(f'prediction {predicted.shape} and truth {truth.shape} differ')
    with np.errstate(over='ignore', invalid='ignore'):
        squared = (predicted - truth) ** 2
    squared = np.where(np.isfinite(squared), squared, np.inf)
    per_step_component = squared.mean(axis=0)
    per_step = per_step_component.mean(axis=1)
    names = dynamics.STATE_NAMES[:truth.shape[2]]
    return {'summed_mse': float(per_step[1:].sum()),
            'final_mse': float(per_step[-1]),
            'mse_per_step': per_step.tolist(),
            'summed_mse_per_component': dict(zip(names, per_step_component[1:].sum(0).tolist()))}
