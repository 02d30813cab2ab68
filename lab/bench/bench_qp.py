"""The koopman_mpc QP solved by DAQP, OSQP and quadprog: time per solve and agreement.

Records the QPs koopman_mpc builds along closed loops on the dynamics module (the comparison
starts, and the paper's start with a tight theta_max so that the soft swing bound and the
tension bounds are active), then solves each recorded QP with every solver. Prints the median
and p99 time per solve, the largest difference of the first move from DAQP's, and how many
QPs had an active bound. Comparison: OSQP (the earlier solver of the law) against DAQP.

The NMPC's QP (the tension changes, dense, DAQP) is timed by bench/bench_nmpc.py and checked
against quadprog by tests/control/test_nmpc.py.
"""

import argparse
import os
import sys
import time

import daqp
import numpy as np
import osqp
import quadprog
import scipy.sparse as sparse

from tsr_koopman_ctrl.control import closed_loop, KoopmanMpc
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, PAPER_START

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402


def record(steps):
    """(hessian, linear, rows, lower, upper) of every QP along the loops."""
    problems = []
    runs = [({}, x0) for x0 in COMPARISON_STARTS] + [({'theta_max': 0.3}, PAPER_START)]
    for settings, x0 in runs:
        mpc = KoopmanMpc(**settings)
        solve = mpc.solve

        def recording_solve(mpc=mpc, solve=solve):
            problems.append((mpc.hessian, mpc.linear.copy(), mpc.rows, mpc.lower.copy(),
                             mpc.upper.copy()))
            return solve()
        mpc.solve = recording_solve
        closed_loop(mpc, x0, steps)
    return problems


def solve_daqp(problem):
    hessian, linear, rows, lower, upper = problem
    return daqp.solve(hessian, linear, rows, upper, lower)[0]


def osqp_solver(problem):
    hessian, linear, rows, lower, upper = problem
    solver = osqp.OSQP()
    constraints = sparse.csc_matrix(np.vstack([np.eye(len(linear)), rows]))
    solver.setup(sparse.triu(hessian, format='csc'), linear, constraints,
                 np.maximum(lower, -1e30), np.minimum(upper, 1e30), verbose=False,
                 warm_starting=True, eps_abs=1e-6, eps_rel=1e-6, max_iter=4000, polishing=True)

    def solve(problem):
        _, linear, _, lower, upper = problem
        solver.update(q=linear, l=np.maximum(lower, -1e30), u=np.minimum(upper, 1e30))
        result = solver.solve(raise_error=False)
        return result.x if result.info.status_val == 1 else np.full(len(linear), np.nan)
    return solve


def solve_quadprog(problem):
    """quadprog: min 1/2 x'Gx - a'x subject to C'x >= b, so each finite bound is a column."""
    hessian, linear, rows, lower, upper = problem
    full = np.vstack([np.eye(len(linear)), rows])
    low, high = np.isfinite(lower), np.isfinite(upper)
    columns = np.vstack([full[low], -full[high]]).T
    bounds = np.r_[lower[low], -upper[high]]
    return quadprog.solve_qp(hessian, -linear, columns, bounds)[0]


def timed(solve, problems):
    times, moves = [], []
    for problem in problems:
        start = time.perf_counter()
        x = solve(problem)
        times.append(time.perf_counter() - start)
        moves.append(x[0])
    times = np.array(times) * 1e6
    return np.median(times), np.percentile(times, 99), np.array(moves)


def active(problem, x, tol=1e-7):
    """True if a tension bound or a swing/overshoot row binds at x (the slack's own s >= 0,
    which binds whenever the soft bounds hold, does not count)."""
    _, _, rows, lower, upper = problem
    values = np.r_[x, rows @ x]
    binding = (values <= lower + tol) | (values >= upper - tol)
    binding[len(x) - 1] = False
    return bool(np.any(binding))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--steps', type=int, help='closed-loop steps per start (default 600)')
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    problems = record(args.steps or 600)
    reference = timed(solve_daqp, problems)
    solvers = {'daqp': solve_daqp, 'osqp (warm, one setup)': osqp_solver(problems[0]),
               'quadprog': solve_quadprog}
    say(f'{len(problems)} QPs ({problems[0][0].shape[0]} variables, '
        f'{problems[0][2].shape[0]} general rows); '
        f"{sum(active(p, solve_quadprog(p)) for p in problems)} with an active bound")
    say(f"{'solver':24s} {'median us':>10s} {'p99 us':>10s} {'not solved':>10s} "
        f"{'max |v1 - daqp| (solved)':>25s}")
    results = {}
    for name, solve in solvers.items():
        median, p99, moves = timed(solve, problems) if name != 'daqp' else reference
        results[name] = median
        solved = np.isfinite(moves)
        say(f'{name:24s} {median:10.1f} {p99:10.1f} {np.sum(~solved):10d} '
            f'{np.max(np.abs(moves[solved] - reference[2][solved])):25.2e}')
    say(f"osqp / daqp (median): {results['osqp (warm, one setup)'] / results['daqp']:.1f}x")
    say.publish()


if __name__ == '__main__':
    main()
