"""Minimum-time deployment of the planar TSR: the frontier a tension law is measured against.

For a start x0 the frontier T*(theta_max) is the least time (tau) in which any tension
0 <= u <= u_max brings the plant to the deployed equilibrium x = 0 (zero rates) while
|theta| <= theta_max on the way. A law that settles in t_s with a measured swing s is then
t_s / T*(s) from optimal (evaluation/frontier.py reads the shipped table this module computes;
lab/frontier.py recomputes it).

Method: direct multiple shooting with a free final time T: N intervals, the tension constant on
each, RK4 inside (the simulator's own integrator, so a returned plan replays exactly through
`tsr_sim.dynamics.rk4_step`). The intervals are T / N except the first few, which are graded
from 2% of that up: at l = 0.01 the Coriolis term 2 l' / l is 100-200 per tau, and the optimum
brakes the tether there in a pulse that a uniform grid can only smear (worst with no upper
tension limit, where it is an impulse). Short-tether intervals also get more RK4 substeps.
IPOPT solves the NLP from several initial guesses (closed loops of linear LQR laws,
time-rescaled, and neighbouring solutions); the best converged one is kept, since the problem
has local optima.

Needs casadi (pip). evaluation/frontier.py, which scores runs, only reads the table and never
imports this module.
"""

import time

import casadi as ca
import numpy as np
from tsr_sim import dynamics
from tsr_sim.dynamics import symbolic_rk4

from tsr_koopman_ctrl.control.lqr import continuous_lqr_gain
from tsr_koopman_ctrl.evaluation.figures import settle_index, ZONE

#: Largest RK4 substep, and the largest fraction of the local time scale l / |l'| per substep.
MAX_SUBSTEP = 0.01
STIFF_FRACTION = 0.2
MAX_SUBSTEPS = 40
#: Relative lengths of the first intervals (the rest are 1): a graded start.
GRADING = (0.02, 0.03, 0.045, 0.07, 0.1, 0.15, 0.23, 0.34, 0.5, 0.76)
#: Interval length (tau) of the restarts, and of the final solve from the best of them.
COARSE_STEP = 0.05
FINE_STEP = 0.025
#: Fewest and most shooting intervals of one NLP.
MIN_INTERVALS, MAX_INTERVALS = 60, 900
#: IPOPT settings of every solve.
IPOPT_OPTIONS = {'ipopt.max_iter': 1500, 'ipopt.tol': 1e-8, 'ipopt.acceptable_tol': 1e-6,
                 'ipopt.mu_strategy': 'adaptive'}
#: LQR weight sets Q = diag(.) whose closed loops seed the NLP: fast and wide, slow and narrow.
GUESS_WEIGHTS = ((1.0, 1.0, 1.0, 1.0), (10.0, 1.0, 10.0, 1.0), (30.0, 10.0, 1.0, 1.0))
#: Swing bounds of the tabulated frontier (None: unconstrained), loosest first.
THETA_GRID = (None, 1.0, 0.8, 0.6, 0.5, 0.4, 0.3)
#: Restarts per bound of the shipped table: two LQR seeds (fast/wide and slow/narrow) at their
#: own settle time, then the previous bound's plan and the fine re-solve. All three seeds at two
#: time scales moved the best T by < 0.1% from the paper's start.
TABLE_OPTIONS = {'guess_weights': GUESS_WEIGHTS[::2], 'duration_scales': (1.0,)}
#: Longest deployment (tau) the least-swing search may take.
LEAST_SWING_CAP = 40.0


def interval_fractions(intervals):
    """Interval lengths as fractions of T: the graded start, then equal intervals."""
    grading = np.array(GRADING[:max(intervals - 1, 0)])
    weights = np.r_[grading, np.ones(intervals - len(grading))]
    return weights / weights.sum()


def lqr_gain(weights):
    """Continuous LQR gain at x = 0, u = 3 for Q = diag(weights), R = 1."""
    return continuous_lqr_gain(weights, 1.0)[0]


def lqr_closed_loop(x0, weights, u_max=dynamics.TENSION_LIMIT, h=0.01, duration=40.0):
    """Closed loop of u = clip(3 - K x) on the plant, an initial guess for the NLP.

    Returns (tau, states, tensions, settle_tau); settle_tau is None if it never settles.
    """
    gain = lqr_gain(weights)
    high = np.inf if u_max is None else u_max
    states, tensions = [np.asarray(x0, dtype=float)], []
    for _ in range(int(round(duration / h))):
        u = float(np.clip(dynamics.EQUILIBRIUM_TENSION - gain @ states[-1], 0.0, high))
        # The float stepper: ~15x faster than rk4_step here, same arithmetic to rounding.
        nxt = dynamics.step(states[-1], u, h, 10)
        if not dynamics.in_domain(nxt):
            break
        tensions.append(u)
        states.append(nxt)
    states = np.array(states)
    tau = h * np.arange(len(states))
    index = settle_index(states)
    return tau, states, np.array(tensions), None if index is None else float(tau[index])


def resample(tau, states, tensions, grid):
    """States at the times `grid` and the tension at the middle of each of its intervals."""
    x = np.column_stack([np.interp(grid, tau, states[:, i]) for i in range(4)])
    mids = 0.5 * (grid[:-1] + grid[1:])
    u = np.interp(mids, 0.5 * (tau[:-1] + tau[1:]), tensions)
    return x, u


def interval_substeps(states, dts):
    """RK4 substeps per interval: enough to resolve l / |l'| on short tethers."""
    length = np.maximum(states[:, 2] + 1.0, 1e-3)
    scale = length / np.maximum(np.abs(states[:, 3]), 1e-6)
    scale = np.minimum(scale[:-1], scale[1:])
    # The guess may be a little off in where l is short: widen the fine region by two intervals.
    scale = np.minimum.reduce([scale, np.r_[scale[1:], np.inf], np.r_[np.inf, scale[:-1]],
                               np.r_[scale[2:], np.inf, np.inf]])
    need = np.maximum(dts / MAX_SUBSTEP, dts / (STIFF_FRACTION * scale))
    return np.clip(np.ceil(need), 1, MAX_SUBSTEPS).astype(int)


def solve_nlp(x0, guess_states, guess_tensions, guess_duration, u_max, theta_max, terminal,
              substeps, tail=3.0, tail_step=0.1, max_iter=IPOPT_OPTIONS['ipopt.max_iter'],
              objective='time', duration_cap=200.0):
    """One IPOPT solve of the minimum-time NLP from one initial guess.

    Decision vector: [T, x_0..x_N, u_0..u_(N-1)] (+ the tail's x and u for terminal='zone').
    terminal='origin': x_N = 0. terminal='zone': |theta_N|, |l_N - 1| <= ZONE and the state
    then stays in the zone for `tail` tau under admissible tension (reached *and kept*, as the
    settle metric asks); the tail is a fixed-length extension outside the objective.
    |theta| <= theta_max holds at every RK4 substep, not only at the nodes.
    objective='swing' minimises max |theta| instead (theta_max ignored, T <= duration_cap):
    the least swing any admissible deployment from x0 can have.
    """
    start = time.perf_counter()
    intervals = len(guess_tensions)
    fractions = interval_fractions(intervals)
    u_high = np.inf if u_max is None else u_max
    duration = ca.SX.sym('T')
    xs = ca.SX.sym('x', 4, intervals + 1)
    us = ca.SX.sym('u', intervals)
    defects, path_theta = [], []
    for k in range(intervals):
        end, path = symbolic_rk4(xs[:, k], us[k], duration * fractions[k], int(substeps[k]))
        defects.append(end - xs[:, k + 1])
        path_theta += [p[0] for p in path[:-1]]
    variables = [duration, ca.vec(xs), us]
    # l >= 1e-3 keeps IPOPT out of the singular l = 0 (where the model has no meaning anyway).
    node_low = np.tile([-np.inf, -np.inf, -0.999, -np.inf], intervals + 1)
    node_high = np.full(4 * (intervals + 1), np.inf)
    if theta_max is not None:
        node_low[0::4], node_high[0::4] = -theta_max, theta_max
    node_low[:4] = node_high[:4] = x0
    if terminal == 'origin':
        node_low[-4:] = node_high[-4:] = 0.0
    else:
        node_low[-4::2], node_high[-4::2] = -ZONE, ZONE
    lbx = [[0.05], node_low, np.zeros(intervals)]
    ubx = [[duration_cap], node_high, np.full(intervals, u_high)]
    x_init = [[guess_duration], guess_states.ravel(), guess_tensions]
    if terminal == 'zone':
        tail_intervals = int(round(tail / tail_step))
        tail_x = ca.SX.sym('xt', 4, tail_intervals)
        tail_u = ca.SX.sym('ut', tail_intervals)
        previous = xs[:, -1]
        for k in range(tail_intervals):
            end, path = symbolic_rk4(previous, tail_u[k], tail_step, 4)
            defects.append(end - tail_x[:, k])
            path_theta += [p[0] for p in path[:-1]]
            previous = tail_x[:, k]
        variables += [ca.vec(tail_x), tail_u]
        zone = np.tile([ZONE, np.inf, ZONE, np.inf], tail_intervals)
        lbx += [-zone, np.zeros(tail_intervals)]
        ubx += [zone, np.full(tail_intervals, u_high)]
        x_init += [np.zeros(4 * tail_intervals),
                   np.full(tail_intervals, dynamics.EQUILIBRIUM_TENSION)]
    constraints = [ca.vertcat(*defects)]
    lbg, ubg = [np.zeros(constraints[0].numel())], [np.zeros(constraints[0].numel())]
    if theta_max is not None and path_theta:
        constraints.append(ca.vertcat(*path_theta))
        lbg.append(np.full(len(path_theta), -theta_max))
        ubg.append(np.full(len(path_theta), theta_max))
    cost = duration
    if objective == 'swing':
        swing = ca.SX.sym('swing')
        thetas = ca.vertcat(xs[0, :].T, *path_theta)
        constraints += [swing - thetas, swing + thetas]
        lbg += [np.zeros(thetas.numel())] * 2
        ubg += [np.full(thetas.numel(), np.inf)] * 2
        variables.append(swing)
        lbx.append([0.0])
        ubx.append([np.inf])
        x_init.append([np.abs(guess_states[:, 0]).max()])
        cost = swing + 1e-4 * duration   # the time term only picks one of many equal swings
    nlp = {'x': ca.vertcat(*variables), 'f': cost, 'g': ca.vertcat(*constraints)}
    options = {**IPOPT_OPTIONS, 'ipopt.print_level': 0, 'print_time': False, 'ipopt.sb': 'yes',
               'ipopt.max_iter': max_iter}
    solver = ca.nlpsol('min_time', 'ipopt', nlp, options)
    result = solver(x0=np.concatenate(x_init), lbx=np.concatenate(lbx),
                    ubx=np.concatenate(ubx), lbg=np.concatenate(lbg), ubg=np.concatenate(ubg))
    w = np.asarray(result['x']).ravel()
    states = w[1:1 + 4 * (intervals + 1)].reshape(intervals + 1, 4)
    # IPOPT relaxes bounds by ~1e-8: put the tension back inside them (moves the nodes < 1e-9).
    tensions = np.clip(w[1 + 4 * (intervals + 1):1 + 5 * intervals + 4], 0.0, u_high)
    stats = solver.stats()
    return {'T': float(w[0]), 'tau': float(w[0]) * np.r_[0.0, np.cumsum(fractions)],
            'states': states, 'tensions': tensions, 'substeps': np.asarray(substeps, dtype=int),
            'success': bool(stats['success']), 'status': stats['return_status'],
            'iterations': int(stats['iter_count']), 'solve_s': time.perf_counter() - start}


def replay(x0, result, substeps=None):
    """Re-simulate a plan open loop with `tsr_sim.dynamics.rk4_step`: states (N + 1, 4).

    substeps: RK4 substeps per interval (default: the plan's own). The deployed equilibrium
    is unstable open loop (eigenvalue ~1.5 per tau), so over long plans solver round-off grows
    e-fold every ~0.7 tau: check those with `interval_defects`."""
    substeps = result['substeps'] if substeps is None else substeps
    states = [np.asarray(x0, dtype=float)]
    for u, dt, m in zip(result['tensions'], np.diff(result['tau']),
                        np.broadcast_to(substeps, len(result['tensions']))):
        states.append(dynamics.rk4_step(states[-1], u, dt, int(m)))
    return np.array(states)


def interval_defects(result, substeps=None):
    """|rk4_step(x_k, u_k, dt_k) - x_(k+1)| per interval (N, 4): how far each node of the plan
    is from its predecessor flown through `tsr_sim.dynamics` (substeps as in `replay`)."""
    substeps = np.broadcast_to(result['substeps'] if substeps is None else substeps,
                               len(result['tensions']))
    states, dts = result['states'], np.diff(result['tau'])
    flown = np.array([dynamics.rk4_step(states[k], result['tensions'][k], dts[k],
                                        int(substeps[k])) for k in range(len(dts))])
    return np.abs(flown - states[1:])


def path_thetas(result):
    """theta at every RK4 substep of a plan, flown interval by interval from its nodes (where
    the swing bound is imposed)."""
    thetas = [result['states'][:, 0]]
    for k, (u, dt, m) in enumerate(zip(result['tensions'], np.diff(result['tau']),
                                       result['substeps'])):
        x = result['states'][k]
        for _ in range(int(m) - 1):
            x = dynamics.rk4_step(x, u, dt / m, 1)
            thetas.append([x[0]])
    return np.concatenate(thetas)


def solve_from_guess(x0, states, tensions, duration, u_max, theta_max, terminal, tail,
                     max_iter):
    """Clip a guess into the bounds, pick substeps for it, solve; re-solve once if the solution
    put short-tether intervals where the guess had too few substeps."""
    states = states.copy()
    if theta_max is not None:
        states[:, 0] = np.clip(states[:, 0], -theta_max, theta_max)
    tensions = np.clip(tensions, 0.0, np.inf if u_max is None else u_max)
    dts = duration * interval_fractions(len(tensions))
    substeps = interval_substeps(states, dts)
    result = solve_nlp(x0, states, tensions, duration, u_max, theta_max, terminal, substeps,
                       tail=tail, max_iter=max_iter)
    need = interval_substeps(result['states'], np.diff(result['tau']))
    if result['success'] and np.any(need > result['substeps']):
        again = solve_nlp(x0, result['states'], result['tensions'], result['T'], u_max,
                          theta_max, terminal, np.maximum(need, result['substeps']),
                          tail=tail, max_iter=max_iter)
        again['solve_s'] += result['solve_s']
        result = again
    return result


def regrid(result, intervals, stretch=1.0):
    """A plan re-sampled on `intervals` graded intervals of its T times `stretch` (rates divided
    by stretch, so a slowed-down copy of the same path)."""
    duration = result['T'] * stretch
    grid = duration * np.r_[0.0, np.cumsum(interval_fractions(intervals))]
    states, tensions = resample(result['tau'] * stretch, result['states'], result['tensions'],
                                grid)
    states[:, [1, 3]] /= stretch
    return states, tensions, duration


def intervals_for(duration, step):
    """Shooting intervals for a plan of `duration` tau at about `step` tau each."""
    return int(np.clip(np.ceil(duration / step), MIN_INTERVALS, MAX_INTERVALS))


def min_time_deployment(x0, u_max=dynamics.TENSION_LIMIT, theta_max=None, terminal='origin',
                        guesses=(), guess_weights=GUESS_WEIGHTS, duration_scales=(1.0, 0.5),
                        tail=3.0, max_iter=IPOPT_OPTIONS['ipopt.max_iter'], refine=True):
    """Minimum-time deployment from x0: 0 <= u <= u_max (u_max None: no upper limit) and
    |theta| <= theta_max (None: free) at every RK4 substep.

    terminal: 'origin' (arrive at x = 0 with zero rates) or 'zone' (enter the 1% zone and stay
    in it for `tail` tau). Initial guesses: the closed loops of LQR laws with Q = diag(w) for w
    in guess_weights, time-scaled to duration_scales of their settle time, and `guesses`: pairs
    (previous result, stretch), that plan slowed down by `stretch`. The best converged solve is
    re-solved on a grid of FINE_STEP (refine).

    Returns a dict: T (tau), tau (N + 1,), states (N + 1, 4), tensions (N,), substeps (N,),
    swing (max |theta| on the path), success, solve_s (all restarts), attempts (one row each).
    """
    x0 = np.asarray(x0, dtype=float)
    started = time.perf_counter()
    attempts, best = [], None
    if theta_max is not None and abs(x0[0]) > theta_max:
        return {'success': False, 'T': np.nan, 'swing': np.nan, 'attempts': attempts,
                'solve_s': 0.0, 'x0': x0, 'status': 'start outside the swing bound'}
    starts = []
    for weights in guess_weights:
        tau, states, tensions, settle = lqr_closed_loop(x0, weights, u_max)
        if settle is None:
            continue
        swing = np.abs(states[:, 0]).max()
        for scale in duration_scales:
            duration = max(settle * scale, 0.5)
            n = intervals_for(duration, COARSE_STEP)
            grid = settle * np.r_[0.0, np.cumsum(interval_fractions(n))]
            gx, gu = resample(tau, states, tensions, grid)
            gx[:, [1, 3]] /= scale
            starts.append((swing, 'lqr', gx, gu, duration))
    # Guesses that already respect the swing bound first, then the given (continuation) ones.
    if theta_max is not None:
        starts.sort(key=lambda s: s[0] > theta_max)
    for previous, stretch in guesses:
        if previous.get('success'):
            n = intervals_for(previous['T'] * stretch, COARSE_STEP)
            starts.append((np.nan, 'given', *regrid(previous, n, stretch)))
    for _, kind, gx, gu, duration in starts:
        result = solve_from_guess(x0, gx, gu, duration, u_max, theta_max, terminal, tail,
                                  max_iter)
        attempts.append(attempt_record(kind, duration, result))
        if result['success'] and (best is None or result['T'] < best['T'] - 1e-6):
            best = result
    if best is not None and refine:
        fine = intervals_for(best['T'], FINE_STEP)
        if fine > len(best['tensions']):
            # Piecewise-constant u costs time on a coarse grid: 8.92 tau at T / N = 0.08
            # against 8.84 at 0.03 for theta_max = 0.4 from the paper's start.
            gx, gu, duration = regrid(best, fine)
            refined = solve_from_guess(x0, gx, gu, duration, u_max, theta_max, terminal, tail,
                                       max_iter)
            attempts.append(attempt_record('refine', duration, refined))
            if refined['success'] and refined['T'] < best['T'] + 1e-6:
                best = refined
    if best is None:
        return {'success': False, 'T': np.nan, 'swing': np.nan, 'attempts': attempts,
                'solve_s': time.perf_counter() - started, 'x0': x0, 'status': 'no solve'}
    best.update(swing=float(np.abs(path_thetas(best)).max()), attempts=attempts,
                solve_s=time.perf_counter() - started, x0=x0, terminal=terminal)
    return best


def attempt_record(kind, guess_duration, result):
    """One restart's summary: its guess, grid, IPOPT status and T."""
    return {'guess': kind, 'guess_T': round(float(guess_duration), 3),
            'N': len(result['tensions']), 'status': result['status'],
            'T': round(result['T'], 4), 'iterations': result['iterations'],
            'solve_s': round(result['solve_s'], 2)}


def zone_entry_tau(result):
    """When a plan enters the 1% zone for good (the settle metric applied to the plan)."""
    index = settle_index(result['states'])
    return float(result['tau'][index]) if index is not None else np.nan


def frontier_table(x0, theta_grid=THETA_GRID, u_max=dynamics.TENSION_LIMIT, terminal='origin',
                   minimum_swing_first=True, progress=None, **options):
    """T*(theta_max) from x0 for each bound, loosest first, each solve also seeded with the
    previous bound's plan slowed down in proportion (continuation: a tight bound's own LQR
    seeds swing far past it). Bounds looser than the unconstrained optimum's swing reuse it;
    bounds under the start's least attainable swing (`minimum_swing`, solved first) are
    infeasible and not attempted; there a bound 0.01 above the least swing is added, since the
    frontier is steep near its left end. The least-swing plan is itself a row (theta_max 'min';
    its T is one plan's, an upper bound of the frontier at that swing).

    progress: called with each row as it is done. options: those of `min_time_deployment`.
    Returns rows (dicts): theta_max, T, swing, solve_s, success, zone_tau (when that plan
    enters the 1% zone for good), result (the full plan), note.
    """
    rows, solved, least = [], [], None

    def add(row):
        rows.append(row)
        if progress is not None:
            progress(row)

    if minimum_swing_first and terminal == 'origin':
        least = minimum_swing(x0, u_max)
    for theta_max in sorted(theta_grid, key=lambda t: -np.inf if t is None else -t):
        free = next((r for r in solved if r['theta_max'] is None), None)
        if free is not None and theta_max is not None and theta_max >= free['swing']:
            add(dict(free, theta_max=theta_max, solve_s=0.0, note='= unconstrained'))
            continue
        if least is not None and theta_max is not None and theta_max < least['swing']:
            add({'theta_max': theta_max, 'T': np.nan, 'swing': np.nan, 'solve_s': 0.0,
                 'success': False, 'zone_tau': np.nan, 'result': None,
                 'note': f'infeasible: least swing {least["swing"]:.3f}'})
            continue
        guesses = [(r['result'], max(1.0, r['swing'] / theta_max) if theta_max else 1.0)
                   for r in solved[-1:]]
        result = min_time_deployment(x0, u_max=u_max, theta_max=theta_max, terminal=terminal,
                                     guesses=guesses, **options)
        add(table_row(theta_max, result, ''))
        if rows[-1]['success']:
            solved.append(rows[-1])
    if least is not None and least['success']:
        # The frontier is steep near its left end: add a point just above the least swing,
        # seeded with the least-swing plan and with the tightest solved one.
        theta_max = round(least['swing'] + 0.01, 3)
        tightest = min((t for t in theta_grid if t is not None), default=np.inf)
        if least['swing'] > tightest:   # only where the grid itself ran out of feasible bounds
            guesses = [(least, 1.0)] + [(r['result'], 1.0) for r in solved[-1:]]
            result = min_time_deployment(x0, u_max=u_max, theta_max=theta_max,
                                         terminal=terminal, guesses=guesses, **options)
            add(table_row(theta_max, result, 'least swing + 0.01'))
        add(table_row('min', least, 'least attainable swing; T is one such plan'))
    return rows


def table_row(theta_max, result, note):
    """A row of `frontier_table` from one `min_time_deployment` (or `minimum_swing`) result."""
    success = bool(result['success'])
    return {'theta_max': theta_max, 'T': result['T'], 'swing': result['swing'],
            'solve_s': result['solve_s'], 'success': success,
            'zone_tau': zone_entry_tau(result) if success else np.nan,
            'result': result, 'note': note if success else result.get('status', 'failed')}


def minimum_swing(x0, u_max=dynamics.TENSION_LIMIT, duration_cap=LEAST_SWING_CAP,
                  guess_weights=GUESS_WEIGHTS[-1:]):
    """The least max |theta| of any deployment from x0 to x = 0 within duration_cap tau: the
    left end of the frontier (below it no tension law, however slow, can keep the swing).
    A local optimum like every other entry: a smaller swing may exist."""
    x0 = np.asarray(x0, dtype=float)
    started = time.perf_counter()
    best = None
    for weights in guess_weights:
        tau, states, tensions, settle = lqr_closed_loop(x0, weights, u_max)
        if settle is None:
            continue
        n = intervals_for(settle, COARSE_STEP)
        grid = settle * np.r_[0.0, np.cumsum(interval_fractions(n))]
        gx, gu = resample(tau, states, tensions, grid)
        substeps = interval_substeps(gx, np.diff(grid))
        result = solve_nlp(x0, gx, gu, settle, u_max, None, 'origin', substeps,
                           objective='swing', duration_cap=duration_cap)
        if result['success']:
            result['swing'] = float(np.abs(path_thetas(result)).max())
            if best is None or result['swing'] < best['swing']:
                best = result
    if best is None:
        return {'success': False, 'T': np.nan, 'swing': np.nan, 'status': 'no solve',
                'solve_s': time.perf_counter() - started}
    best.update(x0=x0, solve_s=time.perf_counter() - started)
    return best
