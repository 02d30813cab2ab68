"""Constrained MPC on the learned lifted linear model (Korda & Mezic 2018): a small dense QP."""

import dataclasses
from typing import ClassVar

import numpy as np
import scipy.linalg
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.koopman_lqr import lifted_state_weight, load_model
from tsr_koopman_ctrl.control.law import Law, planar_state
from tsr_koopman_ctrl.control.lqr import discrete_lqr_gain, prediction_matrices
from tsr_koopman_ctrl.control.settings import cross_weight_setting, LawSettings, setting

#: On koopman_block (observables stable by construction) 30 steps of prediction serve the
#: frontier ratio best: a scan of 3..200 steps with the default weights (docs/tuning.md).
MODEL = 'koopman_block'


@dataclasses.dataclass(frozen=True)
class KoopmanMpcSettings(LawSettings):
    law: ClassVar[str] = 'koopman_mpc'
    model: str = setting(MODEL, 'model directory, or the name of a shipped model')
    # Tuned for the frontier ratio at 30 steps on koopman_block: lab/tune.py --objective
    # worst-ratio --fix model=koopman_block --fix horizon=30, 100 trials, swing <= 0.8 rad
    # (docs/tuning.md); tuned for the mean settle time on koopman_default (horizon 3):
    # config/tuned_settle.yaml; before tuning horizon 5, r = 1, q = 1 (config/untuned.yaml).
    horizon: int = setting(30, 'prediction steps of h', low=1, high=200, tune=(3, 15, 'linear'))
    r: float = setting(2.137, 'weight on the lifted input (its offset from the equilibrium)',
                       low=1e-9, tune=(1e-3, 1e2, 'log'))
    state_weight: str = setting('state', "Q' = C^T diag(q) C on the state ('state') or I on "
                                "the lifted state ('lifted')", choices=('lifted', 'state'))
    q: tuple = setting((67.91, 0.1741, 64.22, 0.159), "state weights q of Q' = C^T diag(q) C",
                       low=0.0, tune=(1e-2, 1e2, 'log'))
    q_cross: tuple = cross_weight_setting()
    theta_max: float = setting(0.8, 'soft bound on |theta| in the prediction [rad]',
                               low=0.01, high=3.2)
    overshoot_max: float = setting(0.05, 'soft bound on l - 1 in the prediction (fraction of '
                                   'the tether length)', low=0.0, high=10.0)
    slack_weight: float = setting(1e4, 'weight of the slack of the soft bounds (s + s^2)',
                                  low=0.0)
    terminal: str = setting('local', "terminal cost: the DARE cost-to-go of the model's own "
                            "linearisation at the target ('local') or of the lifted (A, B) "
                            "('riccati')", choices=('local', 'riccati'))
    qp_solver: str = setting('daqp', "QP solver: 'daqp' (dual active set, made for small dense "
                             "MPC QPs) or 'osqp' (ADMM); same solutions (lab/bench/bench_qp.py)",
                             choices=('daqp', 'osqp'))


class KoopmanMpc(Law):
    """MPC on the lifted model: one QP per step.

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
    (the tether is finite), read through C z_k and soft so the QP is always feasible. Only the
    linear term and the bounds change per step, both affine in the lifted state (precomputed).
    Solved by DAQP (or OSQP); if the solver reports no optimum the last move is repeated and
    `fallbacks` counted.

    The default model is koopman_block, whose observables are stable by construction, with 30
    steps (0.3 tau) of prediction. On the dense koopman_default a short horizon serves better
    (3 steps, config/tuned_settle.yaml): its one-step map is accurate near the path but its
    30-step predictions carry errors that, re-planned every step, stall or tumble the
    deployment (docs/comparison.md: the horizon sweep); the local terminal cost carries the
    long-term goal.
    """

    name = 'koopman_mpc'
    Settings = KoopmanMpcSettings

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        s = self.settings
        self.model, self.horizon = load_model(s.model, linear=True), s.horizon
        a, b = self.model.A, self.model.B
        nz, n_steps = a.shape[0], self.horizon
        q = lifted_state_weight(self.model, s)
        self.z_ref, self.u_hat_ref = self.model.reference()
        # psi_uu(0) and psi_uu(u_max): with psi_ux(x) they bound u_hat at each step.
        self.bound_tension(0.0, self.u_max)
        q_bar = scipy.linalg.block_diag(*([q] * (n_steps - 1) + [self.terminal_weight(q)]))
        free, forced, drift_gain = prediction_matrices(a, b, n_steps)
        drift = drift_gain @ self.reference_drift()
        # Everything but e_0 is fixed: the QP's linear term and the predicted theta and l - 1
        # without input are affine in e_0, so they are two matrix-vector products per step.
        to_cost = 2.0 * forced.T @ q_bar
        self.cost_gain, self.cost_offset = to_cost @ free, to_cost @ drift
        theta, length = slice(dynamics.THETA, None, nz), slice(dynamics.LENGTH_OFFSET, None, nz)
        self.theta_gain = free[theta]
        self.theta_offset = drift[theta] + self.z_ref[dynamics.THETA]
        self.length_gain = free[length]
        self.length_offset = drift[length] + self.z_ref[dynamics.LENGTH_OFFSET]
        hessian = forced.T @ q_bar @ forced + s.r * np.eye(n_steps)
        self.hessian = scipy.linalg.block_diag(2.0 * hessian, [[2.0 * s.slack_weight]])
        # Variables (v_1..v_N, s). Bounds on each first (v in the input range, s >= 0), then
        # theta_k + s >= -theta_max, theta_k - s <= theta_max, l_k - 1 - s <= overshoot_max.
        ones = np.ones((n_steps, 1))
        self.rows = np.block([[forced[theta], ones], [forced[theta], -ones],
                              [forced[length], -ones]])
        self.linear = np.zeros(n_steps + 1)
        self.linear[-1] = s.slack_weight
        self.lower = np.full(n_steps + 1 + 3 * n_steps, -np.inf)
        self.upper = np.full_like(self.lower, np.inf)
        self.lower[n_steps] = 0.0
        self.solve = self.solver_daqp() if s.qp_solver == 'daqp' else self.solver_osqp()
        self.reset()

    def reference_drift(self):
        """d = A z_d + B u_hat_d - z_d: how far the model moves per step from its reference
        (zero for a model trained with `anchor_equilibrium`)."""
        a, b = self.model.A, self.model.B
        return a @ self.z_ref + b[:, 0] * self.u_hat_ref - self.z_ref

    def solver_daqp(self):
        import daqp
        hessian, rows = np.ascontiguousarray(self.hessian), np.ascontiguousarray(self.rows)

        def solve():
            x, _, exitflag, _ = daqp.solve(hessian, self.linear, rows, self.upper, self.lower)
            return x if exitflag == 1 else None
        return solve

    def solver_osqp(self):
        import osqp
        import scipy.sparse as sparse
        solver = osqp.OSQP()
        constraints = np.vstack([np.eye(self.horizon + 1), self.rows])
        solver.setup(sparse.triu(self.hessian, format='csc'), self.linear,
                     sparse.csc_matrix(constraints), np.maximum(self.lower, -1e30),
                     np.minimum(self.upper, 1e30), verbose=False, warm_starting=True,
                     eps_abs=1e-6, eps_rel=1e-6, max_iter=4000, polishing=True)

        def solve():
            solver.update(q=self.linear, l=self.lower, u=self.upper)
            result = solver.solve(raise_error=False)
            return result.x if result.info.status_val == 1 else None
        return solve

    def terminal_weight(self, q):
        if self.settings.terminal == 'riccati':
            return discrete_lqr_gain(self.model.A, self.model.B, q, self.settings.r)[1]
        c = self.model.C
        jacobian, b_x = self.model.local_linear_model()
        return c.T @ discrete_lqr_gain(jacobian, b_x, c @ q @ c.T, self.settings.r)[1] @ c

    def swing_bound(self):
        return self.settings.theta_max

    def limit_tension(self, u_max):
        super().limit_tension(u_max)
        self.bound_tension(0.0, self.u_max)

    def bound_tension(self, low, high):
        """The QP's bounds, on the lifted input: [psi_uu(low), psi_uu(high)] (psi_ux is frozen
        at the measured state in `compute`)."""
        self.input_range = [float(self.model.input_map(u)) for u in (low, high)]

    def reset(self):
        super().reset()
        self.last_move = 0.0
        self.last_tension = None

    def compute(self, x):
        planar = planar_state(x)
        e0 = self.model.psi_x(planar) - self.z_ref
        gain = float(self.model.psi_ux(planar))
        n_steps, settings = self.horizon, self.settings
        self.lower[:n_steps] = gain * self.input_range[0] - self.u_hat_ref
        self.upper[:n_steps] = gain * self.input_range[1] - self.u_hat_ref
        self.linear[:n_steps] = self.cost_gain @ e0 + self.cost_offset
        theta = self.theta_gain @ e0 + self.theta_offset          # predicted with v = 0
        length = self.length_gain @ e0 + self.length_offset
        rows = n_steps + 1
        self.lower[rows:rows + n_steps] = -settings.theta_max - theta
        self.upper[rows + n_steps:rows + 2 * n_steps] = settings.theta_max - theta
        self.upper[rows + 2 * n_steps:] = settings.overshoot_max - length
        solution = self.solve()
        if solution is not None:   # else keep the last move rather than guess
            self.last_move = float(solution[0])
        else:
            self.fallbacks += 1
        self.last_tension = self.model.tension_from_input(
            planar, self.u_hat_ref + self.last_move, gain, guess=self.last_tension)
        return self.last_tension
