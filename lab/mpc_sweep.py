"""Robustness of koopman_mpc, ROS-free: every model x horizon x comparison start.

``python -m lab.mpc_sweep --models koopman_default DIR ... --horizons 5 10 30``
closes the loop on the dynamics module (2000 steps of h = 0.01, as the main job) for each
combination and writes ``mpc_sweep.md`` and ``.json`` under ``--out``: settle time into the 1%
zone and the swing max |theta| per start, and how many runs reached the zone. The DDS loop is
step-identical to this one (tests/test_deploy.py), so the sweep needs no ROS.
"""

import argparse
import os
import sys

import numpy as np
from tqdm import tqdm
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import KoopmanMpc
from tsr_koopman_ctrl.control.koopman_lqr import load_model
from tsr_koopman_ctrl.evaluation import closed_loop_figures, COMPARISON_STARTS
from tsr_koopman_ctrl.model import DEFAULT_MODEL
from tsr_koopman_ctrl import arguments
from lab.report import publish


def run(model, horizon, x0, steps):
    """One closed loop's figures (`evaluation.closed_loop_figures`)."""
    return closed_loop_figures(KoopmanMpc(model=model, horizon=horizon), x0, steps)


def cell(figures):
    if figures['halted']:
        return 'left the domain'
    if figures['settle_tau'] is None:
        final_l = figures['final_state'][dynamics.LENGTH_OFFSET] + 1.0
        return f"not reached (l = {final_l:.2f}, swing {figures['swing']:.2f})"
    return f"{figures['settle_tau']:.2f} ({figures['swing']:.2f})"


def table(results):
    header = ['model', 'horizon', *[f'x0 = {list(x0)}' for x0 in COMPARISON_STARTS], 'reached']
    rows = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    for r in results:
        reached = sum(s['settle_tau'] is not None for s in r['runs'])
        cells = [cell(s) for s in r['runs']]
        rows.append(f"| {r['model']} | {r['horizon']} | " + ' | '.join(cells)
                    + f' | {reached}/{len(cells)} |')
    return '\n'.join(rows)


def parser():
    p = argparse.ArgumentParser(prog='mpc_sweep', description=__doc__.split('\n\n')[0])
    p.add_argument('--models', nargs='+', default=[DEFAULT_MODEL])
    horizon = KoopmanMpc.Settings.__dataclass_fields__['horizon'].metadata
    p.add_argument('--horizons', nargs='+', default=[5],
                   type=arguments.integer(horizon['low'], horizon['high']))
    p.add_argument('--steps', type=arguments.STEPS, default=2000)
    p.add_argument('--out', default=os.path.join('out', 'mpc_sweep'), type=arguments.output_dir)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    try:
        models = {path: load_model(path) for path in args.models}
    except ValueError as error:   # ModelFileError: one line naming the file
        print(f'mpc_sweep: {error}', file=sys.stderr)
        return 2
    results = []
    jobs = [(path, h) for path in args.models for h in args.horizons]
    for path, horizon in tqdm(jobs, desc='model x horizon', file=sys.stdout):
        runs = [run(models[path], horizon, np.array(x0), args.steps) for x0 in COMPARISON_STARTS]
        results.append({'model': path, 'horizon': horizon, 'runs': runs})
    text = ('Settle time into the 1% zone in tau (swing max |theta| in rad), koopman_mpc '
            f'defaults but the horizon, {args.steps} steps.\n\n' + table(results) + '\n')
    publish(args.out, 'mpc_sweep', results, text, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
