"""Constrained MPC on the learned lifted linear model (Korda & Mezic 2018), solved by OSQP."""

import dataclasses
from typing import ClassVar

import numpy as np
import scipy.linalg
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.koopman_lqr import lifted_state_weight, load_model
from tsr_koopman_ctrl.control.law import Law
from tsr_koopman_ctrl.control.lqr import discrete_lqr_gain, prediction_matrices
from tsr_koopman_ctrl.control.settings import LawSettings, setting
from tsr_koopman_ctrl.model.shipped import DEFAULT_MODEL


@dataclasses.dataclass(frozen=True)
class KoopmanMpcSettings(LawSettings):
    law: ClassVar[str] = 'koopman_mpc'
    model: str = setting(DEFAULT_MODEL, 'model directory, or the name of a shipped model')
    horizon: int = setting(5, 'prediction steps of h', low=1, high=200)
    r: float = setting(1.0, 'weight on the lifted input (its offset from the equilibrium)',
                       low=1e-9)
    state_weight: str = setting('state', "Q' = C^T diag(q) C on the state ('state') or I on "
                                "the lifted state ('lifted')", choices=('lifted', 'state'))
    q: tuple = setting((1.0, 1.0, 1.0, 1.0), "state weights q of Q' = C^T diag(q) C", low=0.0)
    theta_max: float = setting(0.8, 'soft bound on |theta| in the prediction [rad]',
                               low=0.01, high=3.2)
    overshoot_max: float = setting(0.05, 'soft bound on l - 1 in the prediction (fraction of '
                                   'the tether length)', low=0.0, high=10.0)
    slack_weight: float = setting(1e4, 'weight of the slack of the soft bounds (s + s^2)',
                                  low=0.0)
    terminal: str = setting('local', "terminal cost: the DARE cost-to-go of the model's own "
                            "linearisation at the target ('local') or of the lifted (A, B) "
                            "('riccati')", choices=('local', 'riccati'))


class KoopmanMpc(Law):
    """MPC on the lifted model: one OSQP QP per step, warm-started.

    Decision: the lifted inputs v_j = u_hat_j - u_hat_d over `horizon` steps and one slack s.
    Predictions e_k = z_k - z_d follow e+ = A e + B v + d, with d = A z_d + B u_hat_d - z_d the
    model's own drift at the reference (zero for a model trained with `anchor_equilibrium`).
    Cost: sum e'Q'e over the horizon, the terminal weight, r sum v_j^2 and `slack_weight`
    (s + s^2). Terminal weight:

    - 'local': C^T P C, P the DARE solution for the model's own linearisation at the reference
      (`LiftedModel.local_linear_model`): a cost-to-go beyond the horizon, read off the learned
      model. Without one the horizon is myopic: even on the exact linearisation the MPC then
      holds u near 3, which reels a short tether in.
    - 'riccati': the lifted DARE's P (with no active constraint the first move is the
      Koopman-LQR move); as ill-conditioned as Koopman-LQR on a learned model.

    Constraints: 0 <= u <= u_max, mapped to bounds on u_hat with psi_ux frozen at the measured
    state (psi_uu is increasing); |theta_k| <= theta_max + s and l_k - 1 <= overshoot_max + s
    (the tether is finite), read through C z_k and soft so the QP is always feasible. Only q and
    the bounds change per step: one OSQP setup. If OSQP does not report "solved" the last move
    is repeated and `fallbacks` counted.

    The default horizon is short (5 steps, 0.05 tau) on purpose: the learned model's one-step
    map is accurate near the path but its 30-step predictions carry errors that, re-planned
    every step, stall or tumble the deployment (README: horizon sweep); the local terminal
    cost carries the long-term goal.
    """

    name = 'koopman_mpc'
    Settings = KoopmanMpcSettings

    def __init__(self, settings=None, **kwargs):
        import osqp
        import scipy.sparse as sparse
        super().__init__(settings, **kwargs)
        s = self.settings
        self.model, self.horizon = load_model(s.model), s.horizon
        a, b = self.model.A, self.model.B
        q = lifted_state_weight(self.model, s)
        self.z_ref, self.u_hat_ref = self.model.reference()
        # psi_uu(0) and psi_uu(u_max): with psi_ux(x) they bound u_hat at each step.
        self.input_range = [float(self.model.input_map(u)) for u in (0.0, self.u_max)]
        n_steps = self.horizon
        weights = [q] * (n_steps - 1) + [self.terminal_weight(q)]
        self.q_bar = scipy.linalg.block_diag(*weights)
        self.free, self.forced, self.drift_gain = prediction_matrices(a, b, n_steps)
        self.drift = a @ self.z_ref + b[:, 0] * self.u_hat_ref - self.z_ref
        hessian = self.forced.T @ self.q_bar @ self.forced + s.r * np.eye(n_steps)
        theta_rows = self.forced[dynamics.THETA::a.shape[0]]   # theta_k from v (N, N)
        length_rows = self.forced[dynamics.LENGTH_OFFSET::a.shape[0]]
        slack, ones = np.zeros((n_steps, 1)), np.ones((n_steps, 1))
        constraints = np.block([[np.eye(n_steps), slack],
                                [theta_rows, ones],
                                [theta_rows, -ones],
                                [length_rows, -ones],
                                [np.zeros((1, n_steps)), np.ones((1, 1))]])
        full_hessian = scipy.linalg.block_diag(2.0 * hessian, [[2.0 * s.slack_weight]])
        self.reset()
        self.solver = osqp.OSQP()
        self.solver.setup(sparse.triu(full_hessian, format='csc'), np.zeros(n_steps + 1),
                          sparse.csc_matrix(constraints),
                          *self.bounds(np.zeros(n_steps * a.shape[0]), -1.0, 1.0),
                          verbose=False, warm_starting=True, eps_abs=1e-6, eps_rel=1e-6,
                          max_iter=4000, polishing=True)

    def terminal_weight(self, q):
        if self.settings.terminal == 'riccati':
            return discrete_lqr_gain(self.model.A, self.model.B, q, self.settings.r)[1]
        c = self.model.C
        jacobian, b_x = self.model.local_linear_model()
        return c.T @ discrete_lqr_gain(jacobian, b_x, c @ q @ c.T, self.settings.r)[1] @ c

    def bounds(self, predicted, u_hat_low, u_hat_high):
        """OSQP's l, u for the free (v = 0) prediction `predicted` of e_1..e_N."""
        n_steps, nz = self.horizon, self.model.A.shape[0]
        theta = predicted[dynamics.THETA::nz] + self.z_ref[dynamics.THETA]
        length = predicted[dynamics.LENGTH_OFFSET::nz] + self.z_ref[dynamics.LENGTH_OFFSET]
        none = np.full(n_steps, np.inf)
        s = self.settings
        low = np.r_[np.full(n_steps, u_hat_low), -s.theta_max - theta, -none, -none, 0.0]
        high = np.r_[np.full(n_steps, u_hat_high), none, s.theta_max - theta,
                     s.overshoot_max - length, np.inf]
        return low, high

    def reset(self):
        super().reset()
        self.last_move = 0.0

    def compute(self, x):
        planar = np.asarray(x, dtype=float)[:self.model.n]
        e0 = self.model.psi_x(planar) - self.z_ref
        gain = float(self.model.psi_ux(planar))
        u_hat_low = gain * self.input_range[0] - self.u_hat_ref
        u_hat_high = gain * self.input_range[1] - self.u_hat_ref
        predicted = self.free @ e0 + self.drift_gain @ self.drift
        linear = np.r_[2.0 * self.forced.T @ self.q_bar @ predicted, self.settings.slack_weight]
        low, high = self.bounds(predicted, u_hat_low, u_hat_high)
        self.solver.update(q=linear, l=low, u=high)
        result = self.solver.solve(raise_error=False)
        if result.info.status_val == 1:   # else keep the last move rather than guess
            self.last_move = result.x[0]
        else:
            self.fallbacks += 1
        return self.model.tension_from_input(planar, self.u_hat_ref + self.last_move)
