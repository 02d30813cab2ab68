"""The model-free laws, the output clamp and the ROS-free loop, on the dynamics module."""

import math

import numpy as np
import pytest
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import (closed_loop, FractionalOrderPd, LinearisedLqr,
                                      make_controller, TensionLimiter)
from tsr_koopman_ctrl.evaluation import run_figures


UNTUNED = {'q': (1.0, 1.0, 1.0, 1.0), 'r': 1.0}


def test_linearised_lqr_deploys_into_the_one_percent_zone():
    states, u = closed_loop(LinearisedLqr(**UNTUNED), dynamics.PAPER_INITIAL_STATE, 2000)
    tau = np.arange(states.shape[0]) * dynamics.PAPER_STEP
    summary = run_figures(tau, states, u)
    # docs/paper_notes.md: ~9.1 tau with theta in [-0.80, 0.02].
    assert summary['settle_tau'] == pytest.approx(9.1, abs=0.05)
    assert summary['theta_min'] == pytest.approx(-0.80, abs=0.01)
    assert summary['theta_max'] == pytest.approx(0.02, abs=0.01)
    assert np.all((u >= 0.0) & (u <= 5.0))


def test_lqr_gain_stabilises_the_linearisation():
    a, b = dynamics.linearise()
    gain = LinearisedLqr().gain
    assert np.linalg.eigvals(a - b @ gain[None, :]).real.max() < 0.0
    assert np.linalg.eigvals(a).real.max() >= 0.0   # the open loop is not


def test_limiter_clamps_and_counts():
    limiter = TensionLimiter(5.0)
    assert [limiter(u) for u in (-1.0, 2.0, 7.0)] == [0.0, 2.0, 5.0]
    assert limiter.clamped == 2
    with pytest.raises(ValueError, match='non-finite'):
        limiter(math.nan)


def test_unknown_controller_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown law 'pid'; choose from"):
        make_controller('pid')


def test_fractional_order_law_deploys_into_the_one_percent_zone():
    controller = FractionalOrderPd()
    states, u = closed_loop(controller, dynamics.PAPER_INITIAL_STATE, 2000)
    summary = run_figures(np.arange(2001) * dynamics.PAPER_STEP, states, u)
    assert summary['settle_tau'] is not None and summary['settle_tau'] < 9.0
    assert np.all((u >= 0.0) & (u <= 5.0))


def test_fractional_derivative_of_order_one_is_the_backward_difference():
    controller = FractionalOrderPd(alpha=1.0, gains=[0.0, 1.0, 0.0, 0.0])
    thetas = [0.0, 0.01, 0.03, 0.06]
    u = [controller.compute([th, 0.0, 0.0, 0.0]) for th in thetas]
    # u = 3 - D theta; D^1 by Grunwald-Letnikov is (theta_k - theta_(k-1)) / h.
    np.testing.assert_allclose(u[1:], 3.0 - np.diff(thetas) / dynamics.PAPER_STEP, atol=1e-9)


def test_fractional_derivative_of_a_ramp_matches_the_closed_form():
    # D^a t = t^(1-a) / Gamma(2-a) (Riemann-Liouville, the ramp starting at t = 0).
    alpha, h = 0.5, 0.01
    controller = FractionalOrderPd(alpha=alpha, gains=[0, 1.0, 0, 0], h=h, memory=1000)
    controller.history = np.zeros(len(controller.weights))   # the ramp is 0 before t = 0
    for k in range(501):
        u = controller.compute([k * h, 0.0, 0.0, 0.0])
    expected = (500 * h) ** (1 - alpha) / math.gamma(2 - alpha)
    assert 3.0 - u == pytest.approx(expected, rel=0.01)


def test_closed_loop_halts_where_the_state_would_leave_the_domain():
    from tsr_koopman_ctrl.control.law import Law

    class ReelIn(Law):   # full tension on a short tether: l reaches 0 within a few tau
        def compute(self, x):
            return 5.0
    states, tensions = closed_loop(ReelIn(), [0.0, 0.0, -0.99, 0.0], 2000)
    assert len(states) == len(tensions) + 1 < 2001
    assert dynamics.in_domain(states).all()
    with np.errstate(all='ignore'):      # the next step leaves the domain or tumbles
        following = dynamics.rk4_step(states[-1], 5.0, 0.01, 10)
    assert not (dynamics.in_domain(following)
                and abs(following[dynamics.THETA]) <= dynamics.TUMBLING_SWING)


def test_limiter_returns_plain_floats_and_counts_in_ints():
    """The node puts both into messages, whose C conversion takes no numpy scalars."""
    limiter = TensionLimiter(5.0)
    limited = limiter(np.float64(7.0))
    assert type(limited) is float and type(limiter.clamped) is int and limiter.clamped == 1


def test_the_untuned_fractional_pd_gains_are_the_untuned_linear_lqr_gains():
    from tsr_koopman_ctrl.control.registry import preset
    np.testing.assert_allclose(preset('untuned')['fractional_pd']['gains'],
                               LinearisedLqr(**UNTUNED).gain, atol=1e-3)


def test_the_cross_terms_make_the_state_weight_the_factor_product():
    q, cross = (4.0, 1.0, 9.0, 0.25), (0.5, -1.0, 2.0, 0.3, 0.0, -0.7)
    # Written out by hand: L with diagonal sqrt(q), the cross terms below it row by row.
    factor = np.array([[2.0, 0.0, 0.0, 0.0], [0.5, 1.0, 0.0, 0.0], [-1.0, 2.0, 3.0, 0.0],
                       [0.3, 0.0, -0.7, 0.5]])
    weight = factor @ factor.T
    law = LinearisedLqr(q=q, q_cross=cross, r=0.3)
    # The gain of the full-matrix CARE, solved here without the project's helper.
    import scipy.linalg
    a, b = dynamics.linearise()
    p = scipy.linalg.solve_continuous_are(a, b, weight, np.array([[0.3]]))
    np.testing.assert_allclose(law.gain, (b.T @ p)[0] / 0.3, rtol=1e-9)
    # Zero cross terms are the diagonal weight the law had before.
    np.testing.assert_array_equal(LinearisedLqr(q=q, r=0.3).gain,
                                  LinearisedLqr(q=q, q_cross=(0.0,) * 6, r=0.3).gain)
    assert not np.allclose(law.gain, LinearisedLqr(q=q, r=0.3).gain)
    with pytest.raises(ValueError, match='q_cross needs 6 numbers'):
        LinearisedLqr(q_cross=(1.0, 2.0))


def test_the_fractional_derivative_keeps_its_time_base_over_dropped_samples():
    """A real-time loop drops states (`Law.elapsed`): the Grunwald-Letnikov sum must not read
    the samples it saw as consecutive. On a ramp, interpolating the dropped ones is exact."""
    h = dynamics.PAPER_STEP
    every, dropping = (FractionalOrderPd(alpha=0.6, gains=[0, 1.0, 0, 0], memory=300)
                       for _ in range(2))
    for k in range(118):
        x = [0.002 * k, 0.0, 0.0, 0.0]
        u_every = every.compute(x)
        if k % 3 == 0:       # the loop answers every third state
            if k:
                dropping.elapsed(3)
            u_dropping = dropping.compute(x)
    assert u_dropping == pytest.approx(u_every, abs=1e-9)
    # Read as consecutive, the same three-times-coarser samples give another derivative.
    naive = FractionalOrderPd(alpha=0.6, gains=[0, 1.0, 0, 0], memory=300)
    for k in range(0, 118, 3):
        u_naive = naive.compute([0.002 * k, 0.0, 0.0, 0.0])
    assert abs(u_naive - u_every) > 0.01 / h ** 0.4
