"""Batch RK4 sampling throughput against a per-trajectory solve_ivp loop, in one run.

Figure: state-steps per second (trajectories x steps / wall time) for the paper's data set
(Table 1 initial states, u uniform in [0, 5], 30 steps of h = 0.01, one RK4 step per sample),
and the ratio to scipy solve_ivp (RK45, rtol 1e-6) integrating each trajectory's 30 zero-order
hold intervals one after the other.
"""

import argparse
import os
import sys
import time

import numpy as np
from scipy.integrate import solve_ivp
from tsr_sim import dynamics

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402


def sample(n, steps, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(dynamics.TABLE1_STATE_LOW, dynamics.TABLE1_STATE_HIGH, (n, 4)),
            rng.uniform(*dynamics.TABLE1_TENSION_RANGE, (n, steps)))


def solve_ivp_loop(x0, u):
    rhs = lambda t, x, uk: dynamics.derivative(x, uk)  # noqa: E731
    for i in range(x0.shape[0]):
        x = x0[i]
        for k in range(u.shape[1]):
            x = solve_ivp(rhs, (0.0, 0.01), x, args=(u[i, k],), rtol=1e-6).y[:, -1]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--trajectories', type=int, default=40_000)
    parser.add_argument('--reference-trajectories', type=int, default=200)
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    steps = 30
    x0, u = sample(args.trajectories, steps)
    start = time.perf_counter()
    states = dynamics.rollout(x0, u, h=0.01, substeps=1)
    batch_s = time.perf_counter() - start
    kept = dynamics.in_domain(states).all(axis=1).sum()
    batch_rate = args.trajectories * steps / batch_s

    n_ref = args.reference_trajectories
    start = time.perf_counter()
    solve_ivp_loop(x0[:n_ref], u[:n_ref])
    ref_s = time.perf_counter() - start
    ref_rate = n_ref * steps / ref_s
    say(f'batch RK4:  {args.trajectories} x {steps} steps in {batch_s:.3f} s = '
        f'{batch_rate:,.0f} state-steps/s ({kept} trajectories stay in the domain)')
    say(f'solve_ivp:  {n_ref} x {steps} steps in {ref_s:.3f} s = {ref_rate:,.0f} '
        f'state-steps/s')
    say(f'ratio batch / solve_ivp loop: {batch_rate / ref_rate:,.0f}x')
    say.publish()


if __name__ == '__main__':
    main()
