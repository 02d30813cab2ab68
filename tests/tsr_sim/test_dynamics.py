"""The dynamics module against an independent high-accuracy reference (scipy solve_ivp)."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from tsr_sim import dynamics

LOW, HIGH = dynamics.TABLE1_STATE_LOW, dynamics.TABLE1_STATE_HIGH


def reference_rhs(t, x, u):
    """The paper's eq. (2)-(3) written out again, scalar, independently of the module."""
    th, w, x3, v = x
    return [w,
            -2.0 * v / (x3 + 1.0) * (w + 1.0) - 3.0 * np.sin(th) * np.cos(th),
            v,
            (x3 + 1.0) * ((w + 1.0) ** 2 + 3.0 * np.cos(th) ** 2 - 1.0) - u]


def reference_rhs_3d(t, x, u):
    th, w, x3, v, b, bd = x
    ell = x3 + 1.0
    return [w,
            2.0 * (w + 1.0) * (bd * np.tan(b) - v / ell) - 3.0 * np.sin(th) * np.cos(th),
            v,
            ell * (bd ** 2 + (w + 1.0) ** 2 * np.cos(b) ** 2
                   + 3.0 * np.cos(th) ** 2 * np.cos(b) ** 2 - 1.0) - u,
            bd,
            -2.0 * v / ell * bd - ((w + 1.0) ** 2 + 3.0 * np.cos(th) ** 2) * np.sin(b) * np.cos(b)]


def reference_step(rhs, x, u, h):
    sol = solve_ivp(rhs, (0.0, h), x, args=(u,), method='DOP853', rtol=1e-12, atol=1e-13)
    return sol.y[:, -1]


def table1_states(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(LOW, HIGH, size=(n, 4)), rng.uniform(0.0, 5.0, size=n)


def test_derivative_matches_reference_on_table1_states():
    x, u = table1_states(200)
    expected = np.array([reference_rhs(0.0, xi, ui) for xi, ui in zip(x, u)])
    np.testing.assert_allclose(dynamics.derivative(x, u), expected, rtol=1e-12, atol=1e-12)


def test_rk4_step_matches_solve_ivp_on_table1_states():
    x, u = table1_states(100, seed=1)
    got = dynamics.rk4_step(x, u, h=0.01, substeps=10)
    want = np.array([reference_step(reference_rhs, xi, ui, 0.01) for xi, ui in zip(x, u)])
    # Worst Table-1 corner (l = 0.01, l' = 2) has a 2 l'/l ~ 400 coefficient: still 1e-7 here.
    np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-7)


def test_single_rk4_step_is_fourth_order():
    x, u = np.array([-0.3, 0.2, -0.5, 0.4]), 2.0
    exact = reference_step(reference_rhs, x, u, 0.2)
    err_h = np.abs(dynamics.rk4_step(x, u, 0.2, substeps=1) - exact).max()
    err_h2 = np.abs(dynamics.rk4_step(x, u, 0.2, substeps=2) - exact).max()
    assert 12.0 < err_h / err_h2 < 20.0  # 2^4 = 16 for a fourth-order method


def test_rollout_matches_solve_ivp_over_30_steps():
    x0, _ = table1_states(20, seed=2)
    x0[:, 2] = np.maximum(x0[:, 2], -0.8)   # away from l -> 0, where the plant runs away
    rng = np.random.default_rng(3)
    u = rng.uniform(0.0, 5.0, size=(20, 30))
    states = dynamics.rollout(x0, u, h=0.01, substeps=4)
    for i in range(20):
        x = x0[i]
        for k in range(30):
            x = reference_step(reference_rhs, x, u[i, k], 0.01)
        np.testing.assert_allclose(states[i, -1], x, atol=1e-8)
    assert states.shape == (20, 31, 4)


def test_3d_model_matches_reference_and_reduces_to_planar():
    x, u = table1_states(30, seed=4)
    rng = np.random.default_rng(5)
    beta = np.column_stack([rng.uniform(-0.5, 0.5, 30), rng.uniform(-0.5, 0.5, 30)])
    x6 = np.hstack([x, beta])
    got = dynamics.rk4_step(x6, u, 0.01, substeps=10)
    want = np.array([reference_step(reference_rhs_3d, xi, ui, 0.01) for xi, ui in zip(x6, u)])
    np.testing.assert_allclose(got, want, atol=1e-7)
    planar = np.hstack([x, np.zeros((30, 2))])
    np.testing.assert_allclose(dynamics.derivative(planar, u)[:, :4],
                               dynamics.derivative(x, u), atol=1e-14)


def test_equilibrium_is_held_by_three():
    x = dynamics.equilibrium_state()
    np.testing.assert_allclose(dynamics.derivative(x, dynamics.EQUILIBRIUM_TENSION), 0.0,
                               atol=1e-15)
    assert np.abs(dynamics.derivative(x, 2.9)).max() > 0.05


def test_linearisation_at_equilibrium_is_the_papers():
    a, b = dynamics.linearise()
    np.testing.assert_array_equal(
        a, [[0, 1, 0, 0], [-3, 0, 0, -2], [0, 0, 0, 1], [0, 2, 3, 0]])
    np.testing.assert_array_equal(b, [[0], [0], [0], [-1]])


def test_linearisation_matches_finite_differences_away_from_equilibrium():
    x, u = np.array([-0.7, 0.3, -0.6, 0.8]), 1.7
    a, b = dynamics.linearise(x, u)
    eps = 1e-6
    fd = np.column_stack([
        (dynamics.derivative(x + eps * e, u) - dynamics.derivative(x - eps * e, u)) / (2 * eps)
        for e in np.eye(4)])
    np.testing.assert_allclose(a, fd, atol=1e-7)
    fd_b = (dynamics.derivative(x, u + eps) - dynamics.derivative(x, u - eps)) / (2 * eps)
    np.testing.assert_allclose(b[:, 0], fd_b, atol=1e-7)


def test_in_domain_flags_nonpositive_length_and_nan():
    states = np.array([[0, 0, -0.5, 0], [0, 0, -1.0, 0], [0, 0, -1.2, 0], [np.nan, 0, 0, 0]])
    assert dynamics.in_domain(states).tolist() == [True, False, False, False]


def test_bad_dimension_is_a_clear_error():
    with pytest.raises(ValueError, match='4 .planar. or 6'):
        dynamics.derivative(np.zeros(5), 0.0)


def test_symbolic_rk4_is_the_simulator_s_rk4():
    import casadi
    x, u = casadi.SX.sym('x', 4), casadi.SX.sym('u')
    end, path = dynamics.symbolic_rk4(x, u, 0.05, 5)
    step = casadi.Function('step', [x, u], [end])
    x0 = np.array([0.1, -0.2, -0.9, 0.5])
    assert len(path) == 5
    np.testing.assert_allclose(np.asarray(step(x0, 2.0)).ravel(),
                               dynamics.rk4_step(x0, 2.0, 0.05, 5), atol=1e-12)
