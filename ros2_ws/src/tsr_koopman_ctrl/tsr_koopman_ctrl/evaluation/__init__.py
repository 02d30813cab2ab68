"""Scoring a deployment: the run's figures (`run_figures`), the comparison starts, the
minimum-time frontier they are divided by, and the plots."""

from tsr_koopman_ctrl.evaluation.figures import (  # noqa: F401
    closed_loop_figures, in_zone, run_figures, settle_index, ZONE)
from tsr_koopman_ctrl.evaluation.frontier import frontier_tau  # noqa: F401
from tsr_koopman_ctrl.evaluation.starts import (  # noqa: F401
    COMPARISON_STARTS, HELD_OUT_STARTS, PAPER_START)
