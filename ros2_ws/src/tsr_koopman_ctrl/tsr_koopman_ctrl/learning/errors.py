"""Multi-step prediction error, the one metric every model is judged by (paper Section IV-C).

A model predicts states (N, T + 1, n) from the true x_0 and the recorded tensions; the error of
a window is its squared difference to the true states, averaged over components and summed over
the T steps. Units: the paper's dimensionless state.

A window whose prediction leaves |x| <= DIVERGED (or turns non-finite) has diverged. Its error is
not a number worth averaging, so every figure states three things: the mean over the windows that
did not diverge, the median over all windows (a diverged one counting as infinite) and the
fraction that diverged. One bad window is then visible without hiding the rest.

Most of a model's error sits in the few windows whose tether gets short (theta'' has a 1/l
term), so the figures also split the windows whose true length dips below SHORT_TETHER from the
rest.
"""

import numpy as np
from tsr_sim import dynamics

#: Far outside the states the plant visits (the data keep |x| <= 10): a prediction beyond it
#: has run away.
DIVERGED = 1e3
#: A window whose true tether length l = 1 + x[2] dips below this is a short-tether window.
SHORT_TETHER = 0.1


def diverged_windows(predicted):
    """(N,) True where a predicted window left |x| <= DIVERGED or turned non-finite."""
    predicted = np.asarray(predicted, dtype=float)
    with np.errstate(invalid='ignore'):
        bounded = np.abs(predicted) <= DIVERGED
    return ~bounded.all(axis=(1, 2))


def multistep_errors(predicted, truth):
    """{'summed_mse', 'summed_mse_median', 'diverged_fraction', 'windows', 'final_mse',
    'mse_per_step' (T+1), 'summed_mse_per_component' (name ->), 'short_tether'}.

    summed_mse, final_mse and the per-step and per-component figures are means over the windows
    that did not diverge (inf if all did); summed_mse_median is over all windows.
    'short_tether': {'fraction' of the windows whose tether dips below SHORT_TETHER,
    'summed_mse' over those and 'rest_summed_mse' over the others (means over the windows that
    did not diverge; None for an empty side), 'share' of the summed squared error theirs}.
    """
    predicted, truth = np.asarray(predicted, dtype=float), np.asarray(truth, dtype=float)
    if predicted.shape != truth.shape:
        raise ValueError(f'prediction {predicted.shape} and truth {truth.shape} differ')
    diverged = diverged_windows(predicted)
    kept = ~diverged
    squared = (predicted[kept] - truth[kept]) ** 2
    names = dynamics.STATE_NAMES[:truth.shape[2]]
    window_sums = np.full(len(truth), np.inf)
    window_sums[kept] = squared.mean(axis=2)[:, 1:].sum(axis=1)
    if kept.any():
        per_step_component = squared.mean(axis=0)
        per_step = per_step_component.mean(axis=1)
        per_component = per_step_component[1:].sum(0)
    else:
        per_step = np.full(truth.shape[1], np.inf)
        per_component = np.full(truth.shape[2], np.inf)
    short = (1.0 + truth[:, :, 2]).min(axis=1) < SHORT_TETHER
    finite = np.isfinite(window_sums)

    def mean(windows):
        return float(window_sums[windows].mean()) if windows.any() else None

    total = window_sums[finite].sum()
    return {'summed_mse': float(per_step[1:].sum()),
            'summed_mse_median': float(np.median(window_sums)),
            'diverged_fraction': float(diverged.mean()),
            'windows': int(len(truth)),
            'final_mse': float(per_step[-1]),
            'mse_per_step': per_step.tolist(),
            'summed_mse_per_component': dict(zip(names, per_component.tolist())),
            'short_tether': {
                'fraction': float(short.mean()),
                'summed_mse': mean(short & finite), 'rest_summed_mse': mean(~short & finite),
                'share': float(window_sums[short & finite].sum() / total) if total else None}}
