"""The linearised closed loop at the target, against scipy's CARE and the plant's Jacobians."""

import numpy as np
import pytest
import scipy.linalg
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.registry import law_class, preset
from lab.local_loop import local_closed_loop


def test_the_linear_lqr_s_local_loop_is_its_continuous_design():
    """u = 3 - K x: the gain read off the law is -K, K from scipy's CARE on the analytic
    Jacobians; the sampled loop's poles are the continuous A - B K's within the 0.01-tau hold."""
    q, r = (4.0, 0.5, 2.0, 0.1), 0.3
    loop = local_closed_loop(law_class('linear_lqr')(q=q, r=r))
    a, b = dynamics.linearise()
    riccati = scipy.linalg.solve_continuous_are(a, b, np.diag(q), np.array([[r]]))
    gain = (b.T @ riccati / r).ravel()
    assert loop['gain'] == pytest.approx(-gain, rel=1e-6)
    expected = np.linalg.eigvals(a - b @ gain[None, :])
    expected = expected[np.argsort(-expected.real)]
    assert np.sort_complex(loop['poles']) == pytest.approx(np.sort_complex(expected), rel=0.03)
    assert loop['slowest_decay'] == pytest.approx(-expected.real.max(), rel=0.03)
    assert np.all(loop['damping'] > 0)


def test_on_koopman_block_the_cross_tuned_koopman_lqr_had_a_lightly_damped_pair():
    """Why its held-out ratios on koopman_block (1.39..1.77) trailed its tuning ones
    (1.25..1.56): near the target its least damped pair is at zeta ~0.22, which starts with
    theta0 = 0 barely excite. On koopman_block_fast (the preset's model) the pair is damped
    like the MPC's and the LQR's (0.58; all above 0.5)."""
    # The best of the --seed 0 cross-term search on koopman_block (docs/tuning.md, q_cross/seed0:
    # 1.558 on the tuning starts, 1.769 held-out), as its record held it.
    on_block = {'model': 'koopman_block', 'state_weight': 'state', 'r': 17.21788437579011,
                'q': [1.0906204110443527, 0.47611922337262974, 4.903295631422893,
                      0.6892152055768881],
                'q_cross': [-0.439780571996781, 0.032703788359989466, 0.009686831418962052,
                            -0.23865143359591223, 0.6649067740576438, -0.018579502995452572]}
    assert local_closed_loop(law_class('koopman_lqr')(**on_block))['damping'].min() < 0.3
    settings = preset('tuned_cross')
    assert settings['koopman_lqr']['model'] == 'koopman_block_fast'
    zeta = {law: local_closed_loop(law_class(law)(**settings[law]))['damping'].min()
            for law in ('linear_lqr', 'koopman_lqr', 'koopman_mpc')}
    assert min(zeta.values()) > 0.5, zeta


def test_near_the_target_the_koopman_lqr_is_the_lqr_of_its_model_s_linearisation():
    """A block model's observables are locally invariant (A maps the lift's Jacobian into
    itself, B lies in it), so the lifted LQR's gain read at the target is the discrete LQR of
    the model's own linearisation with the same Q and R, mapped from u_hat to u (here on
    koopman_block_fast, the cross-tuned preset's model)."""
    from tsr_koopman_ctrl.control.lqr import discrete_lqr_gain, state_cost_matrix
    settings = preset('tuned_cross')['koopman_lqr']
    law = law_class('koopman_lqr')(**settings)
    jacobian, b_x = law.model.local_linear_model()
    local_gain = discrete_lqr_gain(jacobian, np.reshape(b_x, (4, 1)),
                                   state_cost_matrix(settings['q'], settings['q_cross']),
                                   settings['r'])[0]
    # u_hat = psi_ux(x) psi_uu(u): at the target du_hat/du = psi_ux(0) psi_uu'(3).
    model, tension, step = law.model, dynamics.EQUILIBRIUM_TENSION, 1e-6
    slope = (float(model.input_map(tension + step)) - float(model.input_map(tension - step))) \
        / (2 * step) * float(model.psi_ux(np.zeros(4)))
    # u_hat = u_hat_d - K e, so du/dx = -K dpsi/dx / (du_hat/du).
    assert local_closed_loop(law)['gain'] == pytest.approx(-local_gain / slope, rel=1e-3)
