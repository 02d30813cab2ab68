"""Tension controllers behind one interface, ROS-free. All work in the paper's dimensionless
variables: `compute(x)` takes the planar state [theta, theta', l-1, l'] and returns u.

The node (and any closed loop) passes u through `TensionLimiter`, the single output clamp.
"""

import math
import pathlib

import numpy as np
import scipy.linalg
from tsr_sim import dynamics

from tsr_koopman_ctrl import lifted

#: The shipped model, trained with the paper's settings (models/README.md says how).
DEFAULT_MODEL = str(pathlib.Path('models') / 'koopman_default')


class LinearisedLqr:
    """Linearised full-state tension law (Pradeep 1997 type): u = u_eq - K x.

    K is the continuous-time LQR gain of the linearisation at x = 0, u = 3 with weights Q, R.
    Q = I4, R = 1 settles the paper's deployment in ~9.1 tau with theta in [-0.80, 0.02]
    (../shared/TSR_PHYSICS.md; test_controllers.py checks it).
    """

    name = 'linear_lqr'

    def __init__(self, q=None, r=1.0):
        a, b = dynamics.linearise()
        q = np.eye(dynamics.PLANAR_DIM) if q is None else np.asarray(q, dtype=float)
        r = np.atleast_2d(float(r))
        p = scipy.linalg.solve_continuous_are(a, b, q, r)
        self.gain = np.linalg.solve(r, b.T @ p)[0]

    def reset(self):
        pass

    def compute(self, x):
        planar = np.asarray(x)[:dynamics.PLANAR_DIM]
        return dynamics.EQUILIBRIUM_TENSION - float(self.gain @ planar)


class KoopmanLqr:
    """Koopman-LQR (paper Section III-C): discrete LQR on the learned lifted system (A, B).

    u_hat = u_hat_d - K (psi_x(x) - z_d) with z_d = psi_x(0), u_hat_d = psi_u(0, 3), K from the
    discrete Riccati equation with Q' = I (``state_weight='lifted'``, the paper's setting),
    C^T C (``'state'``, the paper's formula Q' = C^T Q C with Q = I) or C^T diag(q) C (four
    numbers), and R' = `r` (15 in the paper); u = psi_uu^-1(u_hat / psi_ux(x)).
    """

    name = 'koopman_lqr'

    def __init__(self, model=DEFAULT_MODEL, r=15.0, state_weight='lifted'):
        self.model = load_model(model)
        self.q = lifted_state_weight(self.model, state_weight)
        self.gain, self.riccati = discrete_lqr_gain(self.model.A, self.model.B, self.q, r)
        self.z_ref, self.u_hat_ref = lifted_reference(self.model)

    def reset(self):
        pass

    def compute(self, x):
        planar = np.asarray(x, dtype=float)[:self.model.n]
        u_hat = self.u_hat_ref - float(self.gain @ (self.model.psi_x(planar) - self.z_ref))
        return self.model.tension_from_input(planar, u_hat)

    def closed_loop_spectral_radius(self):
        a, b = self.model.A, self.model.B
        return float(np.max(np.abs(np.linalg.eigvals(a - b @ self.gain[None, :]))))


class KoopmanMpc:
    """Constrained MPC on the lifted linear model (Korda & Mezic 2018), solved by OSQP.

    Decision: the lifted inputs v_j = u_hat_j - u_hat_d over `horizon` steps and one slack s.
    Predictions e_k = z_k - z_d follow e+ = A e + B v + d, with d = A z_d + B u_hat_d - z_d the
    model's own drift at the reference (zero for a model trained with `anchor_equilibrium`).
    Cost: sum e'Q'e over the horizon (Q' as in `KoopmanLqr`; default C^T C), the terminal
    weight, the input cost and `slack_weight` (s + s^2). Terminal weight:

    - 'local' (default): C^T P C, P the DARE solution for the model's own linearisation at the
      reference (`LiftedModel.local_linear_model`): a cost-to-go beyond the horizon, read off
      the learned model. Without one the horizon is myopic: even on the exact linearisation
      the MPC then holds u near 3, which reels a short tether in.
    - 'riccati': the lifted DARE's P (with no active constraint and input_cost 'level' the first
      move is the Koopman-LQR move); as ill-conditioned as Koopman-LQR on a learned model.
    - 'stage': Q'.

    Input cost: r sum v_j^2 ('level', the LQR's) or r sum (v_j - v_(j-1))^2 with v_(-1) the last
    move ('rate'). Constraints: 0 <= u <= u_max, mapped to bounds on u_hat with psi_ux frozen at
    the measured state (psi_uu is increasing); |theta_k| <= theta_max + s and
    l_k - 1 <= overshoot_max + s (the tether is finite), read through C z_k and soft so the QP
    is always feasible. Only q and the bounds change per step: one OSQP setup, warm-started.
    If OSQP does not report "solved" the last move is repeated and `fallbacks` counted.

    The default horizon is short (5 steps, 0.05 tau) on purpose: the learned model's one-step
    map is accurate near the path but its 30-step predictions carry errors that, re-planned
    every step, stall or tumble the deployment (README: horizon sweep); the local terminal
    cost carries the long-term goal.
    """

    name = 'koopman_mpc'

    def __init__(self, model=DEFAULT_MODEL, horizon=5, r=1.0, state_weight='state',
                 u_max=5.0, theta_max=0.8, overshoot_max=0.05, slack_weight=1e4,
                 terminal='local', input_cost='level'):
        import osqp
        import scipy.sparse as sparse
        self.model, self.horizon, self.u_max = load_model(model), int(horizon), float(u_max)
        self.theta_max, self.overshoot_max = float(theta_max), float(overshoot_max)
        if self.horizon < 1 or not self.u_max > 0.0 or not r > 0.0:
            raise ValueError('horizon must be >= 1, u_max and r > 0')
        if input_cost not in ('level', 'rate'):
            raise ValueError(f"input_cost must be 'level' or 'rate', got {input_cost!r}")
        a, b = self.model.A, self.model.B
        q = lifted_state_weight(self.model, state_weight)
        self.z_ref, self.u_hat_ref = lifted_reference(self.model)
        # psi_uu(0) and psi_uu(u_max): with psi_ux(x) they bound u_hat at each step.
        self.input_range = [float(self.model.input_map(u)) for u in (0.0, self.u_max)]
        n_steps = self.horizon
        weights = [q] * (n_steps - 1) + [self.terminal_weight(terminal, q, r)]
        self.q_bar = scipy.linalg.block_diag(*weights)
        self.free, self.forced, self.drift_gain = prediction_matrices(a, b, n_steps)
        self.drift = a @ self.z_ref + b[:, 0] * self.u_hat_ref - self.z_ref
        self.rate_weight = r if input_cost == 'rate' else 0.0
        difference = np.eye(n_steps) - np.eye(n_steps, k=-1)
        input_weight = difference.T @ difference if input_cost == 'rate' else np.eye(n_steps)
        hessian = self.forced.T @ self.q_bar @ self.forced + r * input_weight
        theta_rows = self.forced[dynamics.THETA::a.shape[0]]   # theta_k from v (N, N)
        length_rows = self.forced[dynamics.LENGTH_OFFSET::a.shape[0]]
        slack, ones = np.zeros((n_steps, 1)), np.ones((n_steps, 1))
        constraints = np.block([[np.eye(n_steps), slack],
                                [theta_rows, ones],
                                [theta_rows, -ones],
                                [length_rows, -ones],
                                [np.zeros((1, n_steps)), np.ones((1, 1))]])
        full_hessian = scipy.linalg.block_diag(2.0 * hessian, [[2.0 * slack_weight]])
        self.slack_weight = slack_weight
        self.reset()
        self.solver = osqp.OSQP()
        self.solver.setup(sparse.triu(full_hessian, format='csc'), np.zeros(n_steps + 1),
                          sparse.csc_matrix(constraints),
                          *self.bounds(np.zeros(n_steps * a.shape[0]), -1.0, 1.0),
                          verbose=False, warm_starting=True, eps_abs=1e-6, eps_rel=1e-6,
                          max_iter=4000, polishing=True)

    def terminal_weight(self, terminal, q, r):
        if terminal == 'stage':
            return q
        if terminal == 'riccati':
            return discrete_lqr_gain(self.model.A, self.model.B, q, r)[1]
        if terminal == 'local':
            c = self.model.C
            jacobian, b_x = self.model.local_linear_model()
            return c.T @ discrete_lqr_gain(jacobian, b_x, c @ q @ c.T, r)[1] @ c
        raise ValueError(f"terminal must be 'local', 'riccati' or 'stage', got {terminal!r}")

    def bounds(self, predicted, u_hat_low, u_hat_high):
        """OSQP's l, u for the free (v = 0) prediction `predicted` of e_1..e_N."""
        n_steps, nz = self.horizon, self.model.A.shape[0]
        theta = predicted[dynamics.THETA::nz] + self.z_ref[dynamics.THETA]
        length = predicted[dynamics.LENGTH_OFFSET::nz] + self.z_ref[dynamics.LENGTH_OFFSET]
        none = np.full(n_steps, np.inf)
        low = np.r_[np.full(n_steps, u_hat_low), -self.theta_max - theta, -none, -none, 0.0]
        high = np.r_[np.full(n_steps, u_hat_high), none, self.theta_max - theta,
                     self.overshoot_max - length, np.inf]
        return low, high

    def reset(self):
        self.fallbacks = 0
        self.last_move = 0.0

    def compute(self, x):
        planar = np.asarray(x, dtype=float)[:self.model.n]
        e0 = self.model.psi_x(planar) - self.z_ref
        gain = float(self.model.psi_ux(planar))
        u_hat_low = gain * self.input_range[0] - self.u_hat_ref
        u_hat_high = gain * self.input_range[1] - self.u_hat_ref
        predicted = self.free @ e0 + self.drift_gain @ self.drift
        linear = np.r_[2.0 * self.forced.T @ self.q_bar @ predicted, self.slack_weight]
        linear[0] -= 2.0 * self.rate_weight * self.last_move
        low, high = self.bounds(predicted, u_hat_low, u_hat_high)
        self.solver.update(q=linear, l=low, u=high)
        result = self.solver.solve(raise_error=False)
        if result.info.status_val == 1:   # else keep the last move rather than guess
            self.last_move = result.x[0]
        else:
            self.fallbacks += 1
        return self.model.tension_from_input(planar, self.u_hat_ref + self.last_move)


def load_model(model):
    """A LiftedModel as given, or loaded from a model directory."""
    return model if isinstance(model, lifted.LiftedModel) else lifted.LiftedModel.load(model)


def lifted_state_weight(model, state_weight):
    """Q' on the lifted state: 'lifted' (I), 'state' (C^T C) or C^T diag(q) C for q of n."""
    c = model.C
    if isinstance(state_weight, str):
        weights = {'lifted': np.eye(c.shape[1]), 'state': c.T @ c}
        if state_weight not in weights:
            raise ValueError(f"state_weight must be 'lifted', 'state' or {c.shape[0]} weights, "
                             f'got {state_weight!r}')
        return weights[state_weight]
    q = np.asarray(state_weight, dtype=float)
    if q.shape != (c.shape[0],) or not np.all(q >= 0.0):
        raise ValueError(f'state weights must be {c.shape[0]} numbers >= 0, got {state_weight!r}')
    return c.T @ np.diag(q) @ c


def lifted_reference(model):
    """(z_d, u_hat_d) = (psi_x(0), psi_u(0, 3)): the deployed equilibrium, lifted."""
    origin = dynamics.equilibrium_state(model.n)
    return model.psi_x(origin), float(model.psi_u(origin, dynamics.EQUILIBRIUM_TENSION))


def prediction_matrices(a, b, steps):
    """e_1..e_N stacked = free e_0 + forced v + drift_gain d for e+ = A e + B v + d."""
    nz = a.shape[0]
    powers = [np.eye(nz)]
    for _ in range(steps):
        powers.append(a @ powers[-1])
    free = np.vstack(powers[1:])
    forced = np.zeros((steps * nz, steps))
    drift_gain = np.zeros((steps * nz, nz))
    for k in range(1, steps + 1):
        rows = slice((k - 1) * nz, k * nz)
        for j in range(k):
            forced[rows, j] = (powers[k - 1 - j] @ b)[:, 0]
        drift_gain[rows] = sum(powers[:k])
    return free, forced, drift_gain


class FractionalOrderPd:
    """Fractional-order tension law (Sun 2014 type, PD^alpha), gains documented here.

    u = 3 - (k_theta theta + k_l (l - 1)) - D^alpha (d_theta theta + d_l (l - 1)), the
    fractional derivative D^alpha by Grunwald-Letnikov over the last `memory` samples of period h
    (history before the first sample taken equal to it). With alpha = 1 this is the linearised
    LQR law with the rates replaced by differenced positions; the default gains are that law's
    (Q = I, R = 1) and alpha = 0.9 adds the fractional operator's memory.
    """

    name = 'fractional_pd'

    def __init__(self, alpha=0.9, gains=None, h=dynamics.PAPER_STEP, memory=200):
        if not 0.0 < alpha <= 1.5:
            raise ValueError(f'alpha must be in (0, 1.5], got {alpha}')
        k = LinearisedLqr().gain if gains is None else np.asarray(gains, dtype=float)
        self.k_theta, self.d_theta, self.k_l, self.d_l = k
        self.alpha, self.h = alpha, h
        weights = [1.0]
        for j in range(1, memory + 1):
            weights.append(weights[-1] * (1.0 - (alpha + 1.0) / j))
        self.weights = np.array(weights) / h ** alpha
        self.reset()

    def reset(self):
        self.history = None

    def compute(self, x):
        x = np.asarray(x, dtype=float)
        signal = self.d_theta * x[dynamics.THETA] + self.d_l * x[dynamics.LENGTH_OFFSET]
        if self.history is None:
            self.history = np.full(len(self.weights), signal)
        self.history = np.roll(self.history, 1)
        self.history[0] = signal
        derivative = float(self.weights @ self.history)
        proportional = self.k_theta * x[dynamics.THETA] + self.k_l * x[dynamics.LENGTH_OFFSET]
        return dynamics.EQUILIBRIUM_TENSION - proportional - derivative


def discrete_lqr_gain(a, b, q, r):
    """K (N,) of u = -K z for z+ = A z + B u minimising sum z'Qz + r u^2, and the DARE's P."""
    if not r > 0.0:
        raise ValueError(f'R must be > 0, got {r}')
    r = np.atleast_2d(float(r))
    try:
        p = scipy.linalg.solve_discrete_are(a, b, q, r)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ValueError(f'no LQR gain for this (A, B): {error} (is it stabilisable?)')
    return np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)[0], p


CONTROLLERS = {LinearisedLqr.name: LinearisedLqr, KoopmanLqr.name: KoopmanLqr,
               KoopmanMpc.name: KoopmanMpc, FractionalOrderPd.name: FractionalOrderPd}


def make_controller(name, **options):
    try:
        cls = CONTROLLERS[name]
    except KeyError:
        raise ValueError(f'unknown controller {name!r}; choose from {sorted(CONTROLLERS)}')
    return cls(**options)


class TensionLimiter:
    """Clamp u into [0, u_max] (a tether cannot push) and count how often it had to."""

    def __init__(self, u_max):
        if not (math.isfinite(u_max) and u_max > 0.0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max}')
        self.u_max = u_max
        self.clamped = 0

    def __call__(self, u):
        if not math.isfinite(u):
            raise ValueError(f'controller produced a non-finite tension {u}')
        limited = min(max(u, 0.0), self.u_max)
        self.clamped += limited != u
        return limited


def closed_loop(controller, x0, steps, h=dynamics.PAPER_STEP, substeps=10, u_max=5.0):
    """Run controller on the dynamics module: returns states (k+1, n) and tensions (k,), k =
    steps unless the state would leave the domain: then the loop halts there, as the
    simulator does, and k < steps."""
    limiter = TensionLimiter(u_max)
    controller.reset()
    states = [np.asarray(x0, dtype=float)]
    tensions = []
    for _ in range(steps):
        u = limiter(controller.compute(states[-1]))
        with np.errstate(all='ignore'):
            nxt = dynamics.rk4_step(states[-1], u, h, substeps)
        if not dynamics.in_domain(nxt):
            break
        tensions.append(u)
        states.append(nxt)
    return np.array(states), np.array(tensions)
