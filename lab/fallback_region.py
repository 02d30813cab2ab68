"""Where the supervisor's fallback holds the plant: the NMPC on the exact equations, offset-free,
flown alone from a grid of states of a deployment (short to full tether, reeling in to paying
out fast, swinging either way), as it is when it takes over from the learned law.

    python -m lab.fallback_region [--theta-max 0.8 0.4] [--steps 1500] [--workers 2]
        [--out lab/results/fallback_region]

A start is held when the run never leaves the domain nor tumbles, keeps |theta| within the swing
bound (+ 0.005 rad) once it is inside it, and settles into the 1% zone within `--steps`.
Writes fallback_region.md (per swing bound: the share held in each (l, l') cell over the
(theta, theta') grid, and every start that is not held), fallback_region.json and a plot
fallback_region.png per bound into --out, and the table into docs/supervisor.md between its
markers.
"""

import argparse
import itertools
import multiprocessing
import os
import sys

import numpy as np
from tsr_sim import dynamics

from lab.report import check_page, marker_name, publish
from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.evaluation import run_figures

#: The grid: tether length l, its rate l', the swing and its rate.
LENGTHS = (0.01, 0.03, 0.1, 0.3, 0.6, 1.0)
LENGTH_RATES = (-0.5, 0.0, 0.5, 1.0)
SWINGS = (-0.3, 0.0, 0.3)
SWING_RATES = (-1.0, 0.0, 0.5)
#: How far past the bound a held run may swing (the NMPC's own margin is 0.003 rad).
TOLERANCE = 0.005
PAGE = os.path.join('docs', 'supervisor.md')


def grid():
    return [(theta, rate, length - 1.0, speed) for length, speed, theta, rate in
            itertools.product(LENGTHS, LENGTH_RATES, SWINGS, SWING_RATES)]


def fly(args):
    """The fallback from `start` with swing bound `theta_max`: its figures and whether it
    held the plant (module docstring)."""
    start, theta_max, steps = args
    law = make_controller('physics_nmpc', theta_max=theta_max)
    try:
        states, tensions = closed_loop(law, start, steps)
    except ValueError:      # no tension for a state: not held
        return {'start': list(start), 'theta_max': theta_max, 'held': False,
                'why': 'no tension'}
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions,
                          halted=len(states) <= steps)
    theta = np.abs(states[:, dynamics.THETA])
    inside = np.flatnonzero(theta <= theta_max)
    past = bool(inside.size and theta[inside[0]:].max() > theta_max + TOLERANCE)
    why = ('left the domain or tumbled' if figures['halted'] else
           'passed the swing bound' if past else
           'did not settle' if figures['settle_tau'] is None else '')
    return {'start': [float(v) for v in start], 'theta_max': theta_max, 'held': not why,
            'why': why, 'settle_tau': figures['settle_tau'], 'swing': figures['swing']}


def table(rows, theta_max):
    """(l, l') cells: the share of the (theta, theta') grid held."""
    mine = [r for r in rows if r['theta_max'] == theta_max]
    lines = [f'Swing bound {theta_max:g} rad: share of the {len(SWINGS) * len(SWING_RATES)} '
             "starts (theta, theta') held, per l (rows) and l' (columns)", '',
             '| l \\\\ l\' | ' + ' | '.join(f'{v:g}' for v in LENGTH_RATES) + ' |',
             '|---' * (len(LENGTH_RATES) + 1) + '|']
    for length in LENGTHS:
        cells = []
        for speed in LENGTH_RATES:
            cell = [r['held'] for r in mine if np.isclose(r['start'][2], length - 1.0)
                    and np.isclose(r['start'][3], speed)]
            cells.append(f'{sum(cell)}/{len(cell)}')
        lines.append(f'| {length:g} | ' + ' | '.join(cells) + ' |')
    failed = [r for r in mine if not r['held']]
    lines += ['', f'Held: {len(mine) - len(failed)} of {len(mine)}.']
    if failed:
        lines += ['Not held (start [theta, theta\', l - 1, l\']: why):', '']
        lines += [f"- {np.round(r['start'], 3).tolist()}: {r['why']}" for r in failed]
    return '\n'.join(lines) + '\n'


def plot(rows, theta_max, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    mine = [r for r in rows if r['theta_max'] == theta_max]
    share = np.array([[np.mean([r['held'] for r in mine
                                if np.isclose(r['start'][2], length - 1.0)
                                and np.isclose(r['start'][3], speed)])
                       for speed in LENGTH_RATES] for length in LENGTHS])
    fig, ax = plt.subplots(figsize=(5, 4))
    image = ax.imshow(share, vmin=0, vmax=1, cmap='RdYlGn', origin='lower', aspect='auto')
    ax.set_xticks(range(len(LENGTH_RATES)), [f'{v:g}' for v in LENGTH_RATES])
    ax.set_yticks(range(len(LENGTHS)), [f'{v:g}' for v in LENGTHS])
    ax.set_xlabel("l' (tether rate)")
    ax.set_ylabel('l (tether length)')
    ax.set_title(f'fallback holds, swing bound {theta_max:g} rad')
    fig.colorbar(image, label="share of (theta, theta') starts held")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def parser():
    p = argparse.ArgumentParser(prog='fallback_region', description=__doc__.split('\n\n')[0])
    p.add_argument('--theta-max', type=float, nargs='+', default=[0.8, 0.4])
    p.add_argument('--steps', type=int, default=1500)
    p.add_argument('--workers', type=int, default=1)
    p.add_argument('--out', default=os.path.join('lab', 'results', 'fallback_region'))
    p.add_argument('--page', default=PAGE, help='the docs page the table is written into')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.page:
        try:
            check_page(args.page, marker_name(args.out))
        except ValueError as error:
            print(f'fallback_region: {error}', file=sys.stderr)
            return 2
    jobs = [(start, theta_max, args.steps) for theta_max in args.theta_max
            for start in grid()]
    print(f'{len(jobs)} runs of {args.steps} steps on {args.workers} worker(s)', flush=True)
    if args.workers > 1:
        with multiprocessing.get_context('spawn').Pool(args.workers) as pool:
            rows = []
            for k, row in enumerate(pool.imap(fly, jobs)):
                rows.append(row)
                print(f'{k + 1}/{len(jobs)}', end='\r', flush=True)
    else:
        rows = [fly(job) for job in jobs]
    text = '\n'.join(table(rows, theta_max) for theta_max in args.theta_max)
    os.makedirs(args.out, exist_ok=True)
    for theta_max in args.theta_max:
        plot(rows, theta_max, os.path.join(args.out, f'fallback_region_{theta_max:g}.png'))
    publish(args.out, 'fallback_region', rows, text, args.page, marker=marker_name(args.out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
