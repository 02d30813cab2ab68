"""Controllers closing the loop on the dynamics module (ROS-free)."""

import math
import pathlib

import numpy as np
import pytest

from tsr_koopman_ctrl import controllers
from tsr_koopman_ctrl.metrics import deployment_summary, OTHER_INITIAL_STATES, settle_index
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


def test_fractional_order_law_deploys_into_the_one_percent_zone():
    controller = controllers.FractionalOrderPd()
    states, u = controllers.closed_loop(controller, dynamics.PAPER_INITIAL_STATE, 2000)
    summary = deployment_summary(np.arange(2001) * dynamics.PAPER_STEP, states, u)
    assert summary['settle_tau'] is not None and summary['settle_tau'] < 9.0
    assert np.all((u >= 0.0) & (u <= 5.0))


def test_fractional_derivative_of_order_one_is_the_backward_difference():
    controller = controllers.FractionalOrderPd(alpha=1.0, gains=[0.0, 1.0, 0.0, 0.0])
    thetas = [0.0, 0.01, 0.03, 0.06]
    u = [controller.compute([th, 0.0, 0.0, 0.0]) for th in thetas]
    # u = 3 - D theta; D^1 by Grunwald-Letnikov is (theta_k - theta_(k-1)) / h.
    np.testing.assert_allclose(u[1:], 3.0 - np.diff(thetas) / dynamics.PAPER_STEP, atol=1e-9)


def test_fractional_derivative_of_a_ramp_matches_the_closed_form():
    # D^a t = t^(1-a) / Gamma(2-a) (Riemann-Liouville, the ramp starting at t = 0).
    alpha, h = 0.5, 0.01
    controller = controllers.FractionalOrderPd(alpha=alpha, gains=[0, 1.0, 0, 0], h=h,
                                               memory=1000)
    controller.history = np.zeros(len(controller.weights))   # the ramp is 0 before t = 0
    for k in range(501):
        u = controller.compute([k * h, 0.0, 0.0, 0.0])
    expected = (500 * h) ** (1 - alpha) / math.gamma(2 - alpha)
    assert 3.0 - u == pytest.approx(expected, rel=0.01)


SHIPPED_MODEL = str(pathlib.Path(__file__).resolve().parents[1] / 'models' / 'koopman_default')


@pytest.mark.parametrize('x0', [dynamics.PAPER_INITIAL_STATE, *OTHER_INITIAL_STATES])
def test_koopman_mpc_with_the_shipped_model_deploys_into_the_one_percent_zone(x0):
    controller = controllers.KoopmanMpc(SHIPPED_MODEL)
    states, u = controllers.closed_loop(controller, x0, 2000)
    summary = deployment_summary(np.arange(2001) * dynamics.PAPER_STEP, states, u)
    assert summary['settle_tau'] is not None and summary['settle_tau'] < 10.0
    assert np.all((u >= 0.0) & (u <= 5.0)) and controller.fallbacks == 0
    assert np.abs(states[:, dynamics.THETA]).max() < 0.85


def test_koopman_lqr_gain_stabilises_the_shipped_lifted_model():
    controller = controllers.KoopmanLqr(SHIPPED_MODEL)
    assert controller.closed_loop_spectral_radius() < 1.0


def exact_linear_lifted_model(lift_dim=2):
    """A LiftedModel whose lifted system is the exact discretised linearisation at x = 0:
    Phi = 0, psi_ux = 1, psi_uu(u) = u - 3, A = blockdiag(expm(A_c h), 0.5 I), B = [B_d; 0]."""
    import scipy.linalg
    from tsr_koopman_ctrl import lifted, model_file
    config = model_file.KoopmanConfig(lift_dim=lift_dim, hidden=3, layers=1, input_hidden=3,
                                      input_layers=1, input_terms=1)
    tensors = {name: np.zeros(shape) for name, shape in model_file.expected_shapes(config).items()}
    tensors['state_std'] = np.ones(4)
    tensors['input_gain.2.bias'] = np.array([np.log(np.expm1(0.95))])   # psi_ux = 1
    tensors['input_map.slope'] = np.array(np.log(np.expm1(2.5 - 1e-3)))   # slope 1 in u
    tensors['input_map.offset'] = np.array(-0.5)                           # psi_uu(3) = 0
    tensors['input_map.amplitude'] = np.array([-50.0])                     # no tanh term
    a_c, b_c = dynamics.linearise()
    h = dynamics.PAPER_STEP
    block = scipy.linalg.expm(np.block([[a_c, b_c], [np.zeros((1, 5))]]) * h)
    tensors['A'] = scipy.linalg.block_diag(block[:4, :4], 0.5 * np.eye(lift_dim))
    tensors['B'] = np.r_[block[:4, 4:], np.zeros((lift_dim, 1))]
    return lifted.LiftedModel(tensors, config), block[:4, :4], block[:4, 4:]


def test_koopman_lqr_on_an_exact_linear_lift_is_the_discrete_lqr():
    model, a_d, b_d = exact_linear_lifted_model()
    assert float(model.input_map(3.0)) == pytest.approx(0.0, abs=1e-9)
    controller = controllers.KoopmanLqr(model, r=1.0, state_weight='state')
    gain, _ = controllers.discrete_lqr_gain(a_d, b_d, np.eye(4), 1.0)
    x = np.array([0.01, -0.02, 0.015, 0.005])
    assert controller.compute(x) == pytest.approx(3.0 - gain @ x, abs=1e-9)
    # ... which deploys like the continuous linearised LQR.
    states, u = controllers.closed_loop(controller, dynamics.PAPER_INITIAL_STATE, 2000)
    summary = deployment_summary(np.arange(2001) * dynamics.PAPER_STEP, states, u)
    assert summary['settle_tau'] is not None and summary['settle_tau'] < 12.0


def test_local_linear_model_of_an_exact_lift_is_the_discretised_linearisation():
    model, a_d, b_d = exact_linear_lifted_model()
    jacobian, b_x = model.local_linear_model()
    np.testing.assert_allclose(jacobian, a_d, atol=1e-8)
    np.testing.assert_allclose(b_x, b_d, atol=1e-12)


def test_mpc_with_the_local_terminal_cost_moves_like_the_discrete_lqr():
    """No active constraint, input cost on the level: the terminal cost-to-go makes the
    finite-horizon MPC the infinite-horizon LQR (Bellman), here against scipy's DARE."""
    model, a_d, b_d = exact_linear_lifted_model()
    mpc = controllers.KoopmanMpc(model, horizon=10, r=1.0, terminal='local',
                                 input_cost='level', u_max=1e6, theta_max=1e6)
    gain, _ = controllers.discrete_lqr_gain(a_d, b_d, np.eye(4), 1.0)
    for x in ([0.01, -0.02, 0.015, 0.005], [-0.05, 0.0, -0.03, 0.02]):
        assert mpc.compute(np.array(x)) == pytest.approx(3.0 - gain @ x, abs=1e-5)
    assert mpc.fallbacks == 0


def test_mpc_sweep_runs_each_model_and_horizon_from_every_start(tmp_path, capsys):
    import json
    from tsr_koopman_ctrl import mpc_sweep
    out = tmp_path / 'sweep'
    assert mpc_sweep.main(['--models', SHIPPED_MODEL, '--horizons', '5', '8', '--steps', '300',
                           '--out', str(out)]) == 0
    results = json.loads((out / 'mpc_sweep.json').read_text())
    assert [r['horizon'] for r in results] == [5, 8]
    assert all(len(r['runs']) == 1 + len(OTHER_INITIAL_STATES) for r in results)
    for r in results:   # the paper's start, against a loop closed here
        states, _ = controllers.closed_loop(controllers.KoopmanMpc(SHIPPED_MODEL,
                                                                   horizon=r['horizon']),
                                            dynamics.PAPER_INITIAL_STATE, 300)
        np.testing.assert_allclose(r['runs'][0]['final_state'], states[-1], atol=1e-12)
    assert '| 5 |' in (out / 'mpc_sweep.md').read_text()
    assert mpc_sweep.main(['--models', str(tmp_path / 'none'), '--out', str(out)]) == 2
    assert 'none: no such model directory' in capsys.readouterr().err


def test_closed_loop_halts_where_the_state_would_leave_the_domain():
    class ReelIn:   # full tension on a short tether: l reaches 0 within a few tau
        def reset(self):
            pass

        def compute(self, x):
            return 5.0
    states, tensions = controllers.closed_loop(ReelIn(), [0.0, 0.0, -0.99, 0.0], 2000)
    assert len(states) == len(tensions) + 1 < 2001
    assert dynamics.in_domain(states).all()
    with np.errstate(all='ignore'):
        assert not dynamics.in_domain(dynamics.rk4_step(states[-1], 5.0, 0.01, 10))
