"""Scoring a deployment: the run's figures (`run_figures`), the comparison starts, the
minimum-time frontier and the plots."""

from tsr_koopman_ctrl.evaluation.figures import run_figures, settle_index, ZONE  # noqa: F401
from tsr_koopman_ctrl.evaluation.frontier import frontier_tau  # noqa: F401
from tsr_koopman_ctrl.evaluation.starts import COMPARISON_STARTS, PAPER_START  # noqa: F401
