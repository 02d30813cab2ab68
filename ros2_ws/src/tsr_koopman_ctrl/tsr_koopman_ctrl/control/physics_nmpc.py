"""Nonlinear MPC on the exact planar model (no learned model): the law a GNC engineer would fly.

Every step `compute(x)` solves, from the measured state, a finite-horizon optimal control
problem on the planar equations of `tsr_sim.dynamics` (multiple shooting, tension piecewise
constant, RK4 inside each interval) with IPOPT through CasADi, and returns the first tension.

Prediction grid: four short lead intervals (h, 2h, 3h, 4h: the first is h, so the move that is
optimised is the move that is flown; near a short tether the Coriolis term 2 l' / l is stiff and
needs 2.5e-3 tau RK4 substeps), then `interval` steps up to `horizon`. The defaults see 3.6 tau
ahead, longer than the whole unconstrained deployment (~2.7 tau), with 39 intervals where a
0.01 tau grid would need 360.

Objective, near time-optimal: a smoothed 1-norm of the state error, with ln l in place of l - 1,
plus the continuous LQR cost-to-go at the target as terminal cost. A quadratic cost fades as the
error shrinks and approaches the 1% zone exponentially (validation runs from the paper's start:
4.4 tau against 2.7 for the 1-norm); on l - 1 a swing-limited deployment from a short tether
stalls (its progress is exponential in l, and a 3.6 tau horizon sees too little of it to pay for
the swing).

Casadi is imported only here, and only when a law is built: the other laws do not need it.
"""

import dataclasses
import hashlib
import math
import os
import pathlib
import subprocess
import tempfile
from typing import ClassVar
import warnings

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.law import Law, planar_state
from tsr_koopman_ctrl.control.lqr import continuous_lqr_gain
from tsr_koopman_ctrl.control.settings import LawSettings, setting

#: theta_max at or above this (a swing past pi is a tumble): no swing bound, a smaller NLP.
NO_SWING_BOUND = math.pi
#: Lead intervals in units of h, and the RK4 substep on them (short tether) and on the rest.
LEAD_STEPS = (1, 2, 3, 4)
LEAD_SUBSTEP = 0.0025
SUBSTEP = 0.025
#: Fixed by the validation runs (not settings): the swing-bound margin for theta between nodes,
#: the exact-penalty weight of the slacks, the 1-norm's smoothing, the cold solve's iterations.
THETA_MARGIN = 0.003
SLACK_WEIGHT = 1e4
SMOOTHING = 0.01
COLD_MAX_ITER = 1000
#: Interpreted-NLP warning given (once per process).
_warned = []


@dataclasses.dataclass(frozen=True)
class PhysicsNmpcSettings(LawSettings):
    law: ClassVar[str] = 'physics_nmpc'
    horizon: float = setting(3.6, 'prediction horizon [tau]', low=0.2, high=20.0)
    interval: float = setting(0.1, 'prediction interval after the four short lead ones [tau]',
                              low=0.01, high=1.0)
    # 0.8 by default: the swing bound every law is tuned and compared under (lab/tune.py).
    theta_max: float = setting(0.8, 'bound on |theta| at every prediction node, soft with an '
                               'exact penalty [rad]; >= pi: no bound', low=0.01, high=3.2)
    q: tuple = setting((10.0, 1.0, 10.0, 1.0), "stage weights on the smoothed |.| of [theta, "
                       "theta', ln l, l']", low=0.0, tune=(1e-1, 1e2, 'log'))
    r: float = setting(0.1, 'stage weight on (u - 3)^2', low=1e-9, tune=(1e-3, 1e1, 'log'))
    overshoot_max: float = setting(0.005, 'bound on l - 1 at every prediction node (fraction '
                                   'of the tether length; soft)', low=0.0, high=10.0)
    max_iter: int = setting(150, 'IPOPT iterations of the warm solve per step', low=1,
                            high=100_000)
    compile: bool = setting(True, 'compile the NLP functions to C with gcc (cached in '
                            '$TSR_NMPC_CACHE or $XDG_CACHE_HOME/tsr_koopman_ctrl; ~4x faster '
                            'steps)')


def cache_dir():
    """Where compiled NLPs are kept: $TSR_NMPC_CACHE, else $XDG_CACHE_HOME/tsr_koopman_ctrl
    (default ~/.cache/tsr_koopman_ctrl)."""
    if os.environ.get('TSR_NMPC_CACHE'):
        return pathlib.Path(os.environ['TSR_NMPC_CACHE'])
    base = os.environ.get('XDG_CACHE_HOME') or pathlib.Path.home() / '.cache'
    return pathlib.Path(base) / 'tsr_koopman_ctrl'


def compiled(solver):
    """A shared library of the solver's NLP functions compiled to C (gcc -O1), keyed by a hash
    of their source. Measured from the paper's start: 15 ms a step compiled, 62 interpreted;
    compiling takes minutes (2.5 on a loaded 2-core machine), once per machine and NLP shape;
    generating the source to hash it, ~2 s per build. None (and one warning) if it cannot be
    built: the caller then solves the interpreted NLP."""
    import casadi as ca
    try:
        with tempfile.TemporaryDirectory() as scratch:
            generator = ca.CodeGenerator('physics_nmpc_nlp.c')
            generator.add(solver.oracle())   # loading looks the NLP up by its name, 'nlp'
            for name in solver.get_function():
                generator.add(solver.get_function(name))
            source = pathlib.Path(generator.generate(scratch + os.sep))
            digest = hashlib.sha1(source.read_bytes()).hexdigest()[:16]
            library = cache_dir() / f'physics_nmpc_{digest}.so'
            if not library.exists():
                library.parent.mkdir(parents=True, exist_ok=True)
                # Built aside and renamed: a concurrent process never loads half a library.
                partial = library.with_suffix(f'.{os.getpid()}.tmp')
                try:
                    subprocess.run(['gcc', '-O1', '-fPIC', '-shared', str(source), '-o',
                                    str(partial), '-lm'], check=True, capture_output=True)
                    partial.replace(library)
                finally:
                    partial.unlink(missing_ok=True)
        return str(library)
    except (OSError, subprocess.CalledProcessError) as error:
        detail = (getattr(error, 'stderr', b'') or b'').decode(errors='replace').strip()
        warn_interpreted(f'cannot compile the NLP ({error}{": " if detail else ""}'
                         f'{detail[:200]})')
        return None


def warn_interpreted(reason):
    """One warning per process that the NLP runs interpreted (slower)."""
    if not _warned:
        _warned.append(reason)
        warnings.warn(f'physics_nmpc: {reason}; solving the NLP interpreted (slower)',
                      RuntimeWarning, stacklevel=4)


def prediction_grid(h, horizon, interval):
    """Interval lengths (tau): the lead ones, then `interval` up to about `horizon`."""
    lead = h * np.array(LEAD_STEPS, dtype=float)
    rest = max(int(round((horizon - lead.sum()) / interval)), 1)
    return np.r_[lead, np.full(rest, interval)]


def shift_plan(plan, starts, durations, age):
    """A plan's tensions (piecewise constant on the grid `starts`, `durations`) as seen `age`
    tau after it was made, on the same grid (the last one held past the horizon)."""
    mids = starts + 0.5 * durations + age
    index = np.searchsorted(np.r_[starts[1:], np.inf], mids, side='right')
    return plan[np.minimum(index, len(plan) - 1)]


class PhysicsNmpc(Law):
    """Nonlinear MPC of the deployment on the exact planar model, solved by IPOPT every step.

    Cost: sum_j d_j [c(y_j) + r (u_j - 3)^2] over the grid (d_j the interval lengths) plus
    y_N' P y_N; y is x with ln l in place of l - 1, c = sum q_i sqrt(y_i^2 + eps^2), P the
    continuous LQR cost-to-go at x = 0, u = 3 for Q = diag(q), R = r (what an infinite horizon
    would price near the target). Constraints: 0 <= u <= u_max; |theta| <= theta_max - margin
    and l - 1 <= overshoot_max at every node, each node with its own slack under an exact (L1)
    penalty: the NLP stays feasible where a bound cannot be met (from some starts no admissible
    tension keeps the swing under it), and binds wherever it can; one slack for all nodes would
    make every violation up to the worst one free. The margin covers theta between nodes. The
    NLP (state and weights as parameters) is built once; IPOPT with the exact Hessian solves it.

    Per step: a warm solve from the previous plan shifted by h (`max_iter` iterations); if it
    fails, a cold one from the closed loop of the linearised LQR law (Q = I, R = 1) on the grid
    (`cold_solves`). If both fail (`fallbacks`), or the new plan costs more than the shifted
    previous plan flown from here (`rejections`: IPOPT fell into a worse local minimum), the
    shifted previous plan is flown; with none yet, the LQR law's.

    Measured (ROS-free loop, h = 0.01 tau, no fallbacks): from the paper's start it settles
    in 2.68 tau unconstrained (swing 1.02), 3.55 with the default theta_max 0.8 (swing 0.797)
    and 9.1 with theta_max 0.4 (swing 0.397; tests check the last two); from the other eight
    comparison and held-out starts, unconstrained, in 2.13..2.65 tau. A step takes 9 ms
    median, 34 ms p99 (bench/bench_compute.py; compiled), against h = 0.01 tau = 8.5 s of
    flight at the paper's orbit rate.
    """

    name = 'physics_nmpc'
    Settings = PhysicsNmpcSettings

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        s = self.settings
        if s.horizon <= self.h * sum(LEAD_STEPS):
            raise ValueError(f'physics_nmpc.horizon must exceed the lead intervals '
                             f'({self.h * sum(LEAD_STEPS):g} tau), got {s.horizon}')
        self.durations = prediction_grid(self.h, s.horizon, s.interval)
        self.starts = np.r_[0.0, np.cumsum(self.durations)[:-1]]
        self.theta_bound = (np.inf if s.theta_max >= NO_SWING_BOUND
                            else s.theta_max - THETA_MARGIN)
        q = np.asarray(s.q, dtype=float)
        terminal = continuous_lqr_gain(q, s.r)[1]
        self.weights = np.r_[q, s.r, terminal.ravel(order='F'), SLACK_WEIGHT, SMOOTHING]
        self.lqr_gain = continuous_lqr_gain(np.ones(4), 1.0)[0]
        self.build()
        self.reset()

    def build(self):
        """The parametric NLP, multiple shooting: decision u_j, node states x_1..x_N and two
        slacks per node; parameter [x0, q, r, P, slack weight, eps], so one compiled solver
        serves every tuning. Shooting keeps the Hessian block-sparse and each interval's RK4
        short (single shooting over the ~180 nested substeps cost ~25 ms per iteration).

        Also `predict(x0, u) -> nodes` (the same RK4, single shooting), `objective(w, p)` (to
        price the shifted previous plan) and `lqr_plan(x0, K)` (the cold start's guess)."""
        import casadi as ca
        from tsr_sim.dynamics import symbolic_rk4     # the plant's one definition
        steps = len(self.durations)
        x0, q, r, eps = ca.SX.sym('x0', 4), ca.SX.sym('q', 4), ca.SX.sym('r'), ca.SX.sym('eps')
        p, slack_weight = ca.SX.sym('P', 4, 4), ca.SX.sym('w')
        u = ca.SX.sym('u', steps)
        nodes = ca.SX.sym('x', 4, steps)
        slack = ca.SX.sym('s', 2, steps)   # theta and length slack per node
        x, shot, cost, defects, predicted = x0, x0, 0, [], []
        substeps = [max(int(np.ceil(d / (LEAD_SUBSTEP if j < len(LEAD_STEPS) else SUBSTEP)
                                    - 1e-9)), 1) for j, d in enumerate(self.durations)]
        u_eq = dynamics.EQUILIBRIUM_TENSION
        for j, d in enumerate(self.durations):
            cost += d * (self.stage_cost(q, x, eps) + r * (u[j] - u_eq) ** 2)
            end, _ = symbolic_rk4(x, u[j], float(d), substeps[j])
            defects.append(end - nodes[:, j])
            x = nodes[:, j]
            shot, _ = symbolic_rk4(shot, u[j], float(d), substeps[j])
            predicted.append(shot)
        self.predict = ca.Function('predict', [x0, u], [ca.horzcat(*predicted)])
        gain, shot, held = ca.SX.sym('K', 4), x0, []
        for j, d in enumerate(self.durations):
            held.append(ca.fmin(ca.fmax(u_eq - ca.dot(gain, shot), 0.0), self.u_max))
            shot, _ = symbolic_rk4(shot, held[-1], float(d), substeps[j])
        self.lqr_plan = ca.Function('lqr_plan', [x0, gain], [ca.vertcat(*held)])
        cost += (ca.bilin(p, self.log_length(x), self.log_length(x))
                 + slack_weight * ca.sum1(ca.vec(slack)))
        thetas, lengths = nodes[0, :].T, nodes[2, :].T
        overshoot = self.settings.overshoot_max
        g = [ca.vertcat(*defects), lengths - slack[1, :].T]
        lbg = [np.zeros(4 * steps), np.full(steps, -np.inf)]
        ubg = [np.zeros(4 * steps), np.full(steps, overshoot)]
        if np.isfinite(self.theta_bound):   # else no theta rows at all: a smaller NLP
            g += [thetas - slack[0, :].T, thetas + slack[0, :].T]
            lbg += [np.full(steps, -np.inf), np.full(steps, -self.theta_bound)]
            ubg += [np.full(steps, self.theta_bound), np.full(steps, np.inf)]
        node_low = np.tile([-np.inf, -np.inf, -0.999, -np.inf], steps)   # l >= 1e-3
        self.bounds = {
            'lbx': np.r_[np.zeros(steps), node_low, np.zeros(2 * steps)],
            'ubx': np.r_[np.full(steps, self.u_max), np.full(6 * steps, np.inf)],
            'lbg': np.concatenate(lbg), 'ubg': np.concatenate(ubg)}
        w = ca.vertcat(u, ca.vec(nodes), ca.vec(slack))
        parameters = ca.vertcat(x0, q, r, ca.vec(p), slack_weight, eps)
        self.objective = ca.Function('objective', [w, parameters], [cost])
        nlp = {'x': w, 'p': parameters, 'f': cost, 'g': ca.vertcat(*g)}
        # No evaluation warnings: IPOPT backs off from a trial point where ln l is undefined,
        # which is routine here, not worth a log line per step.
        options = {'print_time': False, 'show_eval_warnings': False,
                   'ipopt.print_level': 0, 'ipopt.sb': 'yes',
                   'ipopt.max_iter': self.settings.max_iter, 'ipopt.tol': 1e-6,
                   'ipopt.acceptable_tol': 1e-4, 'ipopt.acceptable_iter': 5,
                   'ipopt.warm_start_init_point': 'yes', 'ipopt.warm_start_bound_push': 1e-6,
                   'ipopt.warm_start_mult_bound_push': 1e-6, 'ipopt.mu_init': 1e-3}
        # The cold solver: for the first step and when the warm one fails (a plan that was
        # optimal h ago can sit in a basin IPOPT cannot leave in max_iter iterations).
        cold = {k: v for k, v in options.items() if 'warm_start' not in k}
        cold.update({'ipopt.max_iter': COLD_MAX_ITER, 'ipopt.mu_init': 0.1})
        self.solver = ca.nlpsol('physics_nmpc', 'ipopt', nlp, options)
        library = compiled(self.solver) if self.settings.compile else None
        if library is not None:
            try:
                self.solver = ca.nlpsol('physics_nmpc', 'ipopt', library, options)
            except RuntimeError:   # a damaged cache file: rebuilt once, else interpreted
                pathlib.Path(library).unlink(missing_ok=True)
                library = compiled(self.solver)
                try:
                    if library is not None:
                        self.solver = ca.nlpsol('physics_nmpc', 'ipopt', library, options)
                except RuntimeError as error:
                    warn_interpreted(f'cannot load {library} ({error})')
                    library = None
        self.compiled = library is not None
        self.cold_solver = ca.nlpsol('physics_nmpc_cold', 'ipopt', library or nlp, cold)

    def log_length(self, x):
        """x with ln l in place of l - 1 (equal to first order at l = 1): a swing bound limits
        the deployment rate l' / l, so progress is exponential in l and a cost on l - 1 sees
        almost none of it from a short tether within the horizon (it then holds l)."""
        import casadi as ca
        return ca.vertcat(x[0], x[1], ca.log(1.0 + x[2]), x[3])

    def stage_cost(self, q, x, eps):
        """sum q_i sqrt(y_i^2 + eps^2): a smoothed 1-norm, which keeps pulling hard on small
        errors where a quadratic fades (near time-optimal)."""
        import casadi as ca
        y = self.log_length(x)
        return ca.dot(q, ca.sqrt(y * y + eps * eps))

    def reset(self):
        super().reset()
        steps = len(self.durations)
        self.plan = np.zeros(steps)
        self.has_plan = False
        self.plan_age = 0.0
        self.multipliers = (np.zeros(7 * steps), np.zeros(len(self.bounds['lbg'])))
        self.rejections = 0
        self.cold_solves = 0
        #: IPOPT iterations of the last step and its last status ('' if it solved).
        self.iterations = 0
        self.last_failure = ''

    def shifted_plan(self, age):
        return shift_plan(self.plan, self.starts, self.durations, age)

    def candidate(self, x, tensions):
        """A plan flown open loop from x: the decision vector (nodes, the slacks it needs) and
        its objective; (None, inf) if it leaves the model's domain."""
        nodes = np.asarray(self.predict(x, tensions)).T
        if not np.all(dynamics.in_domain(nodes)):
            return None, np.inf
        theta_slack = np.maximum(0.0, np.abs(nodes[:, 0]) - self.theta_bound)
        length_slack = np.maximum(0.0, nodes[:, 2] - self.settings.overshoot_max)
        w = np.r_[tensions, nodes.ravel(), np.column_stack([theta_slack, length_slack]).ravel()]
        return w, float(self.objective(w, np.r_[x, self.weights]))

    def solve(self, solver, guess, x, multipliers):
        result = solver(x0=guess, p=np.r_[x, self.weights], lam_x0=multipliers[0],
                        lam_g0=multipliers[1], **self.bounds)
        stats = solver.stats()
        self.iterations += int(stats['iter_count'])
        solved = stats['success'] or stats['return_status'] == 'Solved_To_Acceptable_Level'
        if not solved:
            self.last_failure = stats['return_status']
        return result, solved

    def compute(self, x):
        planar = planar_state(x)
        self.iterations, self.last_failure = 0, ''
        steps = len(self.durations)
        age = self.plan_age + self.h
        guess, guess_cost = (self.candidate(planar, self.shifted_plan(age)) if self.has_plan
                             else (None, np.inf))
        solved = False
        if guess is not None:
            result, solved = self.solve(self.solver, guess, planar, self.multipliers)
        if not solved:
            self.cold_solves += 1
            cold_plan = np.asarray(self.lqr_plan(planar, self.lqr_gain)).ravel()
            cold_guess, _ = self.candidate(planar, cold_plan)
            if cold_guess is not None:
                no_multipliers = [np.zeros_like(m) for m in self.multipliers]
                result, solved = self.solve(self.cold_solver, cold_guess, planar,
                                            no_multipliers)
        cost = float(result['f']) if solved else np.inf
        if solved and cost <= guess_cost + 1e-6 * (1.0 + abs(guess_cost)):
            solution = np.asarray(result['x']).ravel()
            self.plan = np.clip(solution[:steps], 0.0, self.u_max)
            self.plan_age = 0.0
            self.multipliers = (np.asarray(result['lam_x']).ravel(),
                                np.asarray(result['lam_g']).ravel())
        elif guess is not None:   # fly the shifted previous plan
            self.fallbacks += not solved
            self.rejections += solved
            self.plan_age = age
        else:   # nothing solved and no plan yet: fly the LQR law's
            self.fallbacks += 1
            self.plan = np.asarray(self.lqr_plan(planar, self.lqr_gain)).ravel()
            self.plan_age = 0.0
        self.has_plan = True
        return float(self.shifted_plan(self.plan_age)[0])
