"""Nonlinear MPC on the learned model, relifted every step, by real-time iteration.

`koopman_mpc` rolls the lifted model as a linear system, which is accurate for ~30 steps and
diverges beyond (README, *What this shows*); so its plans are short and it cannot plan like the
physics NMPC. Relifted before every step, the same learned model is a one-step map
x+ = C (A psi_x(x) + B psi_u(x, u)) that stays accurate over a whole deployment. This law plans
on that map over the physics NMPC's grid and cost, and solves it the cheap way: one convex QP
per step on the map linearised along the previous plan (real-time iteration, Diehl et al. 2005),
instead of an NLP.

Per step: the previous plan shifted by h and flown on the map from the measured state with
the LQR gain on the deviation from the path it predicted (`shifted_plan`; the first step: the
linearised LQR law flown on the map, refined by COLD_ITERATIONS QP steps);
each interval's sensitivities to its start state and tension, exact (the networks
differentiated in forward mode, the one-step Jacobians chained over the interval, all intervals
in one batch); then the QP in the plan's change du (condensed:
the node states are affine in du):

    min  sum_j d_j (q . t_j + r (u_j - 3)^2) + y_N' P y_N + 1e4 sum_j s_j
    s.t. -t_j <= y_j <= t_j,  |theta_j| <= theta_max - margin + s_j,  s_j >= 0,
         0 <= u_j <= u_max,  |du_j| <= trust

with y = [theta, theta', ln l, l'] linearised at the nodes (the physics NMPC's 1-norm through
slacks t, exact instead of smoothed), the physics NMPC's margin for theta between nodes and P
the continuous LQR cost-to-go at the target. The plan moves by du (halved until the new
plan's rollout keeps the tether longer than LENGTH_FLOOR) and its first tension is flown.
Solved by Clarabel (interior point on the sparse problem; `qp_solver: quadprog`, dense
Goldfarb-Idnani, solves it exactly at 3.9x the time, bench/bench_qp.py, and backs Clarabel up
where it reports no optimum at full accuracy): DAQP cycles on this degenerate, LP-like QP (it
failed on half the steps of a deployment from the paper's start, 2026-11-30), quadprog on
none. A failed solve keeps the shifted plan and counts a fallback. The default model is
koopman_retrieval (MODEL, below).
"""

import dataclasses
from typing import ClassVar

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.koopman_lqr import load_model
from tsr_koopman_ctrl.control.law import Law, planar_state
from tsr_koopman_ctrl.control.lqr import continuous_lqr_gain
from tsr_koopman_ctrl.control.physics_nmpc import (
    PhysicsNmpcSettings as Nmpc, prediction_grid, shift_plan, THETA_MARGIN)
from tsr_koopman_ctrl.control.settings import LawSettings, setting

#: The QP's regularisation of its variables (a strictly convex QP) and the weight of the swing
#: slacks: fixed by the first runs.
REGULARISATION = 1e-2
SLACK_WEIGHT = 1e4

#: QP iterations on the first step (from the LQR plan), and halvings of a QP step whose plan
#: leaves the model's domain before the step is refused.
COLD_ITERATIONS = 5
BACKTRACKS = 4
#: Clarabel's gap and feasibility tolerances (its default 1e-8 moved a planned tension by up to
#: 7e-4 against quadprog's exact active-set solution on 64 QPs of a deployment; 1e-10, 2e-5).
CLARABEL_TOLERANCE = 1e-10
#: The plans keep the predicted tether this long at least (half the paper's initial length):
#: the learned map is not trusted on a tether about to be reeled in completely.
LENGTH_FLOOR = 0.005

#: A fast deployment brakes by reeling the tether back in (l' < 0 at l < 1), which the paper's
#: data never show: on koopman_default the plan mispredicts the braking, the tether overshoots
#: and the last centimetres take a tau (frontier ratio up to 1.58). koopman_retrieval is
#: koopman_default fine-tuned with retrieval data too (models/README.md).
MODEL = 'koopman_retrieval'


@dataclasses.dataclass(frozen=True)
class KoopmanNmpcSettings(LawSettings):
    law: ClassVar[str] = 'koopman_nmpc'
    model: str = setting(MODEL, 'model directory, or the name of a shipped model')
    # The physics NMPC's defaults (hand-picked there; not tuned here: ~0.13 s a step).
    horizon: float = setting(Nmpc.horizon, 'prediction horizon [tau]', low=0.2, high=20.0)
    interval: float = setting(Nmpc.interval, 'prediction interval after the four short lead '
                              'ones [tau], a multiple of the step h', low=0.01, high=1.0)
    theta_max: float = setting(Nmpc.theta_max, 'bound on |theta| at every prediction node, '
                               'soft with an exact penalty [rad]', low=0.01, high=3.2)
    q: tuple = setting(Nmpc.q, "stage weights on |.| of [theta, theta', ln l, l']", low=0.0,
                       tune=(1e-1, 1e2, 'log'))
    r: float = setting(Nmpc.r, 'stage weight on (u - 3)^2', low=1e-9, tune=(1e-3, 1e1, 'log'))
    warm_start: str = setting('feedback', "each step's first plan: the last one shifted by h "
                              "and flown with the LQR gain on the deviation from its predicted "
                              "path ('feedback'), or merely shifted ('shift'; under a 0.4 swing "
                              'bound it held the bound from one start more, README)',
                              choices=('feedback', 'shift'))
    qp_solver: str = setting('clarabel', "QP solver: 'clarabel' (interior point, sparse: 3.9x "
                             'faster here; quadprog where it reports no full-accuracy optimum) '
                             "or 'quadprog' (dense active set, exact; the law's solver until "
                             '2026-12-01)', choices=('clarabel', 'quadprog'))
    trust: float = setting(2.0, 'largest change of a planned tension per step (the QP trusts '
                           'the linearisation that far)', low=1e-3, high=10.0)


def in_model_domain(nodes):
    """True if a rollout stays finite and keeps the tether longer than LENGTH_FLOOR."""
    return bool(np.all(np.isfinite(nodes))
                and np.all(nodes[:, dynamics.LENGTH_OFFSET] > LENGTH_FLOOR - 1.0))


class KoopmanNmpc(Law):
    """Real-time-iteration NMPC on the relifted learned model (module docstring)."""

    name = 'koopman_nmpc'
    Settings = KoopmanNmpcSettings

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        s = self.settings
        self.model = load_model(s.model)
        self.durations = prediction_grid(self.h, s.horizon, s.interval)
        self.counts = np.rint(self.durations / self.h).astype(int)
        if not np.allclose(self.counts * self.h, self.durations) or np.any(self.counts < 1):
            raise ValueError(f'koopman_nmpc.interval must be a multiple of h = {self.h:g}, got '
                             f'{s.interval}')
        self.starts = np.r_[0.0, np.cumsum(self.durations)[:-1]]
        self.q = np.asarray(s.q, dtype=float)
        self.terminal = continuous_lqr_gain(self.q, s.r)[1]
        self.lqr_gain = continuous_lqr_gain(np.ones(4), 1.0)[0]
        self.reset()

    def reset(self):
        super().reset()
        self.plan = self.plan_nodes = None
        #: Steps since the plan was made (it ages when a solve fails).
        self.plan_age = 0.0

    def fly(self, x, tension):
        """Fly the map from x over the grid, interval j at `tension(j, state at its start)`:
        (plan (N,), node states (N + 1, n))."""
        x = np.asarray(x, dtype=float)
        plan, nodes, state = [], [x], x[None]
        for j, count in enumerate(self.counts):
            plan.append(tension(j, state[0]))
            for _ in range(count):
                state = self.model.step(state, np.array([plan[-1]]))
            nodes.append(state[0])
        return np.array(plan), np.array(nodes)

    def lqr_plan(self, x):
        """The linearised LQR law (Q = I, R = 1) flown on the map over the grid, a first plan:
        (plan, its rollout)."""
        u_eq = dynamics.EQUILIBRIUM_TENSION
        return self.fly(x, lambda j, state: float(np.clip(u_eq - self.lqr_gain @ state, 0.0,
                                                          self.u_max)))

    def rollout(self, x, plan):
        """The node states (N + 1, n) of `plan` flown on the map from x."""
        return self.fly(x, lambda j, state: plan[j])[1]

    def sensitivities(self, nodes, plan):
        """(A_j, b_j): d x_{j+1} / d x_j (N, n, n) and / d u_j (N, n), exact: each interval's
        one-step Jacobians (`LiftedModel.step_jacobians`, forward mode through the networks)
        chained over its steps, all intervals in one batch, stepped up to the longest."""
        n = self.model.n
        states = np.array(nodes[:-1], dtype=float)
        a = np.broadcast_to(np.eye(n), (len(plan), n, n)).copy()
        b = np.zeros((len(plan), n))
        for k in range(int(self.counts.max())):
            active = self.counts > k
            states[active], d_state, d_tension = self.model.step_jacobians(
                states[active], plan[active])
            a[active] = d_state @ a[active]
            b[active] = np.einsum('nij,nj->ni', d_state, b[active]) + d_tension
        return a, b

    def node_gains(self, nodes, plan):
        """(N, n, N): node j+1 moves by gains[j] @ du, to first order, when the plan moves by
        du (the intervals' sensitivities chained; the start state is measured, fixed)."""
        a, b = self.sensitivities(nodes, plan)
        n_nodes = len(plan)
        gains = np.zeros((n_nodes, self.model.n, n_nodes))
        running = np.zeros((self.model.n, n_nodes))
        for j in range(n_nodes):
            running = a[j] @ running
            running[:, j] += b[j]
            gains[j] = running
        return gains

    def compute(self, x):
        x = planar_state(x)
        cold = self.plan is None
        plan, nodes = (self.lqr_plan(x) if cold else
                       self.shifted_plan(x, self.plan_age + self.h))
        if not in_model_domain(nodes):
            plan, nodes = self.lqr_plan(x)      # the shifted plan leaves the model's domain
            if not in_model_domain(nodes):
                nodes = None
        new_plan = None
        for _ in range(COLD_ITERATIONS if cold else 1):
            step = None if nodes is None else self.iterate(x, nodes, plan)
            if step is None:
                break
            plan, nodes = step
            new_plan = plan
        if new_plan is None:
            self.fallbacks += 1
            if self.plan is None or nodes is None:   # fly the LQR plan just made
                self.plan, self.plan_age, self.plan_nodes = plan, 0.0, nodes
            else:                                    # fly the previous plan on
                self.plan_age += self.h
            return float(shift_plan(self.plan, self.starts, self.durations, self.plan_age)[0])
        self.plan, self.plan_age, self.plan_nodes = new_plan, 0.0, nodes
        return float(self.plan[0])

    def shifted_plan(self, x, age):
        """The warm start: the previous plan seen `age` later, flown from x on the map with the
        LQR gain on the deviation from the previous plan's predicted path; (plan, its rollout).

        The length dynamics are unstable open loop (the plant's 1.0128 per step), so the plain
        shifted plan, its switches now h later, predicts a path that drifts off within the
        3.6-tau horizon, and one trust-limited QP step repairs only part of that. From
        (0, 0, -0.95, 1.0), steps 5..120: the plain shifted plans predicted a length overshoot of
        0.27 (median; up to 0.55) where the plans they came from predicted 0.018; with the
        feedback, 0.031 (up to 0.042) against 0.0085. Frontier ratio 0.99..1.17 from the nine
        starts instead of 1.03..1.20 (2026-11-30)."""
        shifted = shift_plan(self.plan, self.starts, self.durations, age)
        if self.settings.warm_start == 'shift' or self.plan_nodes is None:
            return shifted, self.rollout(x, shifted)   # (no path: the LQR plan after a failure)
        times = np.r_[self.starts, self.starts[-1] + self.durations[-1]]
        wanted = np.minimum(self.starts + age, times[-1])
        reference = np.stack([np.interp(wanted, times, self.plan_nodes[:, i])
                              for i in range(self.model.n)], axis=1)
        return self.fly(x, lambda j, state: float(np.clip(
            shifted[j] - self.lqr_gain @ (state - reference[j]), 0.0, self.u_max)))

    def iterate(self, x, nodes, plan):
        """One QP step from `plan` (its rollout `nodes`), shortened until the new plan's rollout
        stays in the model's domain: (new plan, its rollout), or None. Near a short tether the
        linearisation is poor: a full step that brakes hard can pull the predicted length
        through zero, and a plan that leaves the domain cannot be linearised at all."""
        du = self.solve(nodes, plan)
        if du is None:
            return None
        for _ in range(BACKTRACKS):
            candidate = np.clip(plan + du, 0.0, self.u_max)
            candidate_nodes = self.rollout(x, candidate)
            if in_model_domain(candidate_nodes):
                return candidate, candidate_nodes
            du = 0.5 * du
        return None

    def solve(self, nodes, plan):
        """The QP of the module docstring: du, or None if the solver fails."""
        solve = solve_clarabel if self.settings.qp_solver == 'clarabel' else solve_quadprog
        solution = solve(*self.qp_problem(nodes, plan))
        return None if solution is None else solution[:len(plan)]

    def qp_problem(self, nodes, plan):
        """(hessian, linear, rows, bounds) of the QP in [du, t, s]: min 1/2 v' H v + linear' v
        subject to rows v >= bounds."""
        s, n_nodes = self.settings, len(plan)
        gains = self.node_gains(nodes, plan)
        states = nodes[1:]
        length = np.maximum(1.0 + states[:, dynamics.LENGTH_OFFSET], 1e-6)
        y = states.copy()
        y[:, dynamics.LENGTH_OFFSET] = np.log(length)
        y_gains = gains.copy()
        y_gains[:, dynamics.LENGTH_OFFSET] /= length[:, None]
        # Variables [du (N), t (4N), s (N)].
        n_t = y.size
        terminal = y_gains[-1]
        hessian = REGULARISATION * np.eye(n_nodes + n_t + n_nodes)
        hessian[:n_nodes, :n_nodes] += 2.0 * (s.r * np.diag(self.durations)
                                              + terminal.T @ self.terminal @ terminal)
        linear = np.r_[2.0 * (s.r * self.durations * (plan - dynamics.EQUILIBRIUM_TENSION)
                              + terminal.T @ self.terminal @ y[-1]),
                       (self.durations[:, None] * self.q[None, :]).ravel(),
                       np.full(n_nodes, SLACK_WEIGHT)]
        to_y = y_gains.reshape(n_t, n_nodes)
        theta = gains[:, dynamics.THETA, :]
        eye_t, eye_s = np.eye(n_t), np.eye(n_nodes)
        none_t, none_s = np.zeros((n_t, n_nodes)), np.zeros((n_nodes, n_t))
        # Rows r with r . v >= bound (quadprog's form).
        rows = np.block([
            [-to_y, eye_t, none_t], [to_y, eye_t, none_t],                   # t >= |y|
            [-theta, none_s, eye_s], [theta, none_s, eye_s],                 # |theta| <= max + s
            [np.eye(n_nodes), none_s, np.zeros((n_nodes, n_nodes))],         # du >= lower
            [-np.eye(n_nodes), none_s, np.zeros((n_nodes, n_nodes))],        # du <= upper
            [np.zeros((n_nodes, n_nodes + n_t)), eye_s]])                    # s >= 0
        bounds = np.r_[y.ravel(), -y.ravel(),
                       states[:, dynamics.THETA] - (s.theta_max - THETA_MARGIN),
                       -states[:, dynamics.THETA] - (s.theta_max - THETA_MARGIN),
                       np.maximum(-plan, -s.trust), -np.minimum(self.u_max - plan, s.trust),
                       np.zeros(n_nodes)]
        return hessian, linear, rows, bounds


def solve_quadprog(hessian, linear, rows, bounds):
    """argmin 1/2 v' H v + linear' v subject to rows v >= bounds, or None."""
    import quadprog
    try:
        return quadprog.solve_qp(hessian, -linear, rows.T, bounds, 0)[0]
    except ValueError:    # quadprog: constraints inconsistent or matrix not positive definite
        return None


def solve_clarabel(hessian, linear, rows, bounds):
    """The same QP by Clarabel (interior point, sparse), in its form -rows v + s = -bounds with
    s >= 0; where it reports no optimum at full accuracy (one QP of 400 from (0, 0, -0.95, 1.0),
    'AlmostSolved'), quadprog's exact solution; None if that fails too."""
    import clarabel
    from scipy import sparse
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = CLARABEL_TOLERANCE
    solver = clarabel.DefaultSolver(
        sparse.triu(hessian, format='csc'), linear, sparse.csc_matrix(-rows), -bounds,
        [clarabel.NonnegativeConeT(len(bounds))], settings)
    solution = solver.solve()
    if str(solution.status) != 'Solved':
        return solve_quadprog(hessian, linear, rows, bounds)
    return np.asarray(solution.x)
