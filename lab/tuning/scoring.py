"""A trial's score: the law closed on the dynamics module (step-identical to the DDS loop) from
each start, the starts' figures combined per objective, a start that misses scored the
penalty."""

import numpy as np

from tsr_koopman_ctrl.control import make_controller
from tsr_koopman_ctrl.evaluation import closed_loop_figures, COMPARISON_STARTS
from tsr_koopman_ctrl.evaluation.starts import SWING_TUNING_STARTS

#: Score of a start that does not settle, halts or swings too far: twice the 20-tau run.
PENALTY_TAU = 40.0
#: The same for the ratio objectives: ten times the minimum time.
PENALTY_RATIO = 10.0
#: A run that does not settle under the 'swing' objective (a tumble is beyond pi anyway).
PENALTY_SWING = 10.0
#: A graded miss counts at most this much above the penalty (a law that cannot be built).
MISS_CAP = 10.0
#: objective -> (figure a start scores, its penalty, how the starts' scores combine, the
#: score's name in the report)
OBJECTIVES = {'settle': ('settle_tau', PENALTY_TAU, 'mean', 'mean settle tau'),
              'ratio': ('frontier_ratio', PENALTY_RATIO, 'mean', 'mean frontier ratio'),
              'worst-ratio': ('frontier_ratio', PENALTY_RATIO, 'max', 'largest frontier ratio'),
              'swing': ('swing', PENALTY_SWING, 'max', 'largest swing [rad]')}
#: --starts -> the tuning starts a trial deploys from (never a held-out one).
TUNING_STARTS = {'comparison': COMPARISON_STARTS,
                 'swing': COMPARISON_STARTS + SWING_TUNING_STARTS}


def score(law, settings, starts, swing_max, steps, objective='settle', graded=False):
    """(score over starts per `objective`, per-start figures), the law built as the node builds
    it (offset-free by default). A law that cannot be built scores the penalty everywhere
    (`graded`: plus MISS_CAP); with `graded` a start that misses scores the penalty plus
    `miss`."""
    figure, penalty, combine, _ = OBJECTIVES[objective]
    try:
        controller = make_controller(law, **settings)
    except ValueError as error:
        return penalty + (MISS_CAP if graded else 0.0), [{'error': str(error)}] * len(starts)
    bound = None if figure == 'swing' else swing_max   # 'swing': how far, whatever the bound
    runs, scores = [], []
    for start in starts:
        figures = closed_loop_figures(controller, start, steps)
        missed = miss(figures, bound)
        if missed == 0.0 and figures[figure] is not None:
            scores.append(figures[figure])
        else:   # (a settled run of a start without a tabulated frontier has no ratio)
            scores.append(penalty + (missed if graded else 0.0))
        runs.append(figures)
    return (max(scores) if combine == 'max' else sum(scores) / len(scores)), runs


def miss(figures, swing_max=None):
    """How far a run missed: radians past `swing_max` (None: no bound) plus one if it did not
    settle, at most MISS_CAP; 0.0 for a run that counts."""
    past = 0.0 if swing_max is None else max(0.0, figures['swing'] - swing_max)
    unsettled = 1.0 if figures['settle_tau'] is None else 0.0
    total = past + unsettled
    return MISS_CAP if not np.isfinite(total) else min(total, MISS_CAP)
