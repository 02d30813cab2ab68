"""The figures of a run: settle time, swing, tension integral, frontier ratio."""

import numpy as np
import pytest

from tsr_koopman_ctrl.evaluation import run_figures, settle_index


def test_settle_index_needs_to_stay_in_the_zone():
    inside, outside = [0.0, 0, 0.005, 0], [0.5, 0, 0, 0]
    assert settle_index(np.array([outside, inside, outside, inside, inside])) == 3
    assert settle_index(np.array([inside, outside])) is None


@pytest.mark.parametrize('tau, states', [(np.zeros(0), np.zeros((0, 4))),
                                         (np.zeros(3), np.zeros((2, 4))),
                                         (np.zeros(4), np.zeros(4))])
def test_run_figures_of_no_run_or_mismatched_arrays_is_one_line(tau, states):
    with pytest.raises(ValueError, match=r'run_figures takes tau \(N,\) and states \(N, n\)'):
        run_figures(tau, states, np.zeros(1))
