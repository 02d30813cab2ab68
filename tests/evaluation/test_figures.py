"""The figures of a run: settle time, swing, tension integral, frontier ratio."""

import numpy as np

from tsr_koopman_ctrl.evaluation import settle_index


def test_settle_index_needs_to_stay_in_the_zone():
    inside, outside = [0.0, 0, 0.005, 0], [0.5, 0, 0, 0]
    assert settle_index(np.array([outside, inside, outside, inside, inside])) == 3
    assert settle_index(np.array([inside, outside])) is None
