"""Controllers closing the loop on the dynamics module (ROS-free)."""

import math

import numpy as np
import pytest

from tsr_koopman_ctrl import controllers
from tsr_koopman_ctrl.metrics import deployment_summary, settle_index
from tsr_sim import dynamics


def test_linearised_lqr_deploys_into_the_one_percent_zone():
    states, u = controllers.closed_loop(controllers.LinearisedLqr(),
                                        dynamics.PAPER_INITIAL_STATE, 2000)
    tau = np.arange(states.shape[0]) * dynamics.PAPER_STEP
    summary = deployment_summary(tau, states, u)
    # ../shared/TSR_PHYSICS.md: ~9.1 tau with theta in [-0.80, 0.02].
    assert summary['settle_tau'] == pytest.approx(9.1, abs=0.05)
    assert summary['theta_min'] == pytest.approx(-0.80, abs=0.01)
    assert summary['theta_max'] == pytest.approx(0.02, abs=0.01)
    assert np.all((u >= 0.0) & (u <= 5.0))


def test_lqr_gain_stabilises_the_linearisation():
    a, b = dynamics.linearise()
    gain = controllers.LinearisedLqr().gain
    assert np.linalg.eigvals(a - b @ gain[None, :]).real.max() < 0.0
    assert np.linalg.eigvals(a).real.max() >= 0.0   # the open loop is not


def test_limiter_clamps_and_counts():
    limiter = controllers.TensionLimiter(5.0)
    assert [limiter(u) for u in (-1.0, 2.0, 7.0)] == [0.0, 2.0, 5.0]
    assert limiter.clamped == 2
    with pytest.raises(ValueError, match='non-finite'):
        limiter(math.nan)


def test_unknown_controller_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown controller 'pid'; choose from"):
        controllers.make_controller('pid')


def test_settle_index_needs_to_stay_in_the_zone():
    inside, outside = [0.0, 0, 0.005, 0], [0.5, 0, 0, 0]
    assert settle_index(np.array([outside, inside, outside, inside, inside])) == 3
    assert settle_index(np.array([inside, outside])) is None
