"""The identification excitation: bounded, seeded, shaped as its settings say."""

import numpy as np
import pytest

from tsr_koopman_ctrl.control.excitation import Excitation


def test_off_by_default():
    assert not Excitation().active and Excitation().next() == 0.0


def test_prbs_holds_plus_or_minus_the_amplitude():
    source = Excitation(kind='prbs', amplitude=0.4, hold=5, seed=1)
    values = np.array([source.next() for _ in range(200)])
    assert set(np.round(np.abs(values), 12)) == {0.4}
    blocks = values.reshape(-1, 5)
    assert np.all(blocks == blocks[:, :1])             # held for `hold` steps
    assert 0.3 < np.mean(blocks[:, 0] > 0) < 0.7       # both levels
    again = Excitation(kind='prbs', amplitude=0.4, hold=5, seed=1)
    assert [again.next() for _ in range(200)] == values.tolist()


def test_noise_is_bounded_and_low_pass():
    source = Excitation(kind='noise', amplitude=0.2, hold=20, seed=2)
    values = np.array([source.next() for _ in range(5000)])
    assert np.abs(values).max() <= 0.2 and values.std() > 0.05
    # A first-order filter with a 20-step time constant: neighbours correlate ~exp(-1/20).
    correlation = np.corrcoef(values[:-1], values[1:])[0, 1]
    assert correlation == pytest.approx(np.exp(-1 / 20), abs=0.05)
