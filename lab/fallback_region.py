"""Where the supervisor's fallback holds the plant: the NMPC on the exact equations, offset-free,
flown alone from a grid of states of a deployment (short to full tether, reeling in to paying
out fast, swinging either way), as it is when it takes over from the learned law.

    python -m lab.fallback_region [--theta-max 0.8 0.4] [--steps 1500] [--runs N]
        [--workers 2 | --address ADDR] [--out lab/results/fallback_region]

Flies lab/campaigns/fallback_region.yaml (the start grid, physics_nmpc alone, one law per swing
bound) through the product's campaign API (`tsr_koopman_ctrl.campaign`, resumed where --out
holds its rows). A start is held when the run never leaves the domain nor tumbles, keeps
|theta| within the swing bound (+ SWING_TOLERANCE, 0.005 rad; every start of the grid begins
within it), and settles into the 1% zone within the steps. Writes fallback_region.md (per
swing bound: the share held in each (l, l') cell over the (theta, theta') grid, and every
start that is not held), fallback_region.json and a plot fallback_region_<bound>.png per
bound into --out, and the table into docs/supervisor.md between its markers.
"""

import argparse
import math
import os
import sys

import numpy as np

from lab.campaigns import add_engine_options, fly, spec_path
from lab.report import check_page, marker_name, publish
from tsr_koopman_ctrl.evaluation.figures import SWING_TOLERANCE

SPEC = spec_path('fallback_region.yaml')
LAW = 'physics_nmpc'
PAGE = os.path.join('docs', 'supervisor.md')


def bound_law(theta_max):
    """The grid's law for one swing bound."""
    return {'law': LAW, 'label': f'theta_max_{theta_max:g}'.replace('.', '_'),
            'set': [f'{LAW}.theta_max={theta_max!r}']}


def bound(entry):
    return entry.settings[LAW]['theta_max']


def load(theta_max=None, steps=None, runs=None):
    """The study's campaign: the spec's, with other swing bounds, steps or runs if given.
    ValueError where a start begins past a bound (the held rule reads the run's largest swing,
    so it needs every start within the bound)."""
    from tsr_koopman_ctrl.campaign import load_spec
    laws = None if theta_max is None else [bound_law(value) for value in theta_max]
    campaign = load_spec(SPEC, laws=laws, steps=steps, runs=runs)
    widest = max(abs(x0[0]) for x0 in campaign.start_list)
    for entry in campaign.laws:
        if entry.law != LAW or 'theta_max' not in entry.settings.get(LAW, {}):
            raise ValueError(f'{SPEC}: law {entry.label}: each law is {LAW} with its '
                             'theta_max set')
        if widest > bound(entry):
            raise ValueError(f'swing bound {bound(entry):g}: the grid starts at |theta| up to '
                             f'{widest:g}, past it')
    return campaign


def verdict(row, theta_max):
    """Why a run (a campaign row) did not hold the plant under `theta_max`; '' if it did."""
    if row['error']:
        return 'no tension'
    if row['halted']:
        return 'left the domain or tumbled'
    if row['swing'] > theta_max + SWING_TOLERANCE:
        return 'passed the swing bound'
    return 'did not settle' if math.isnan(row['settle_tau']) else ''


def results(campaign, rows):
    """One result per (bound, start) flown, bound by bound in the grid's order (l, l', theta,
    theta'): start, theta_max, held, why, settle_tau (None: not settled), swing."""
    laws = [entry.label for entry in campaign.laws]
    bounds = {entry.label: bound(entry) for entry in campaign.laws}
    flown = []
    for row in rows.to_dict('records'):
        theta_max, why = bounds[row['law']], verdict(row, bounds[row['law']])
        start = [float(row[f'x0_{i}']) for i in range(4)]
        order = (laws.index(row['law']), start[2], start[3], start[0], start[1])
        flown.append((order, {
            'start': start, 'theta_max': theta_max, 'held': not why, 'why': why,
            'settle_tau': None if math.isnan(row['settle_tau']) else float(row['settle_tau']),
            'swing': None if math.isnan(row['swing']) else float(row['swing'])}))
    return [result for _, result in sorted(flown, key=lambda pair: pair[0])]


def axes(campaign):
    """The grid's values: (lengths l, rates l', swings theta, swing rates theta')."""
    def values(i):
        return sorted({x0[i] for x0 in campaign.start_list})
    return [v + 1.0 for v in values(2)], values(3), values(0), values(1)


def cell_rows(rows, length, speed):
    return [r for r in rows if np.isclose(r['start'][2], length - 1.0)
            and np.isclose(r['start'][3], speed)]


def table(rows, theta_max, campaign):
    """(l, l') cells: the share of the (theta, theta') grid held."""
    lengths, rates, swings, swing_rates = axes(campaign)
    mine = [r for r in rows if r['theta_max'] == theta_max]
    lines = [f'Swing bound {theta_max:g} rad: share of the {len(swings) * len(swing_rates)} '
             "starts (theta, theta') held, per l (rows) and l' (columns)", '',
             '| l \\\\ l\' | ' + ' | '.join(f'{v:g}' for v in rates) + ' |',
             '|---' * (len(rates) + 1) + '|']
    for length in lengths:
        cells = []
        for speed in rates:
            cell = [r['held'] for r in cell_rows(mine, length, speed)]
            cells.append(f'{sum(cell)}/{len(cell)}')
        lines.append(f'| {length:g} | ' + ' | '.join(cells) + ' |')
    failed = [r for r in mine if not r['held']]
    lines += ['', f'Held: {len(mine) - len(failed)} of {len(mine)}.']
    if failed:
        lines += ['Not held (start [theta, theta\', l - 1, l\']: why):', '']
        lines += [f"- {np.round(r['start'], 3).tolist()}: {r['why']}" for r in failed]
    return '\n'.join(lines) + '\n'


def plot(rows, theta_max, campaign, path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    lengths, rates, _, _ = axes(campaign)
    mine = [r for r in rows if r['theta_max'] == theta_max]
    share = np.array([[np.mean([r['held'] for r in cell_rows(mine, length, speed)] or [np.nan])
                       for speed in rates] for length in lengths])
    fig, ax = plt.subplots(figsize=(5, 4))
    image = ax.imshow(share, vmin=0, vmax=1, cmap='RdYlGn', origin='lower', aspect='auto')
    ax.set_xticks(range(len(rates)), [f'{v:g}' for v in rates])
    ax.set_yticks(range(len(lengths)), [f'{v:g}' for v in lengths])
    ax.set_xlabel("l' (tether rate)")
    ax.set_ylabel('l (tether length)')
    ax.set_title(f'fallback holds, swing bound {theta_max:g} rad')
    fig.colorbar(image, label="share of (theta, theta') starts held")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def parser():
    p = argparse.ArgumentParser(prog='fallback_region', description=__doc__.split('\n\n')[0])
    p.add_argument('--theta-max', type=float, nargs='+',
                   help="swing bounds, one law each (default: the spec's, 0.8 and 0.4)")
    p.add_argument('--steps', type=int, help="steps per run (default: the spec's, 1500)")
    p.add_argument('--runs', type=int, help='the first N starts of the grid (default: all)')
    add_engine_options(p)
    p.add_argument('--out', default=os.path.join('lab', 'results', 'fallback_region'))
    p.add_argument('--page', default=PAGE, help='the docs page the table is written into')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    try:
        if args.page:
            check_page(args.page, marker_name(args.out))
        campaign = load(args.theta_max, args.steps, args.runs)
        rows = fly(campaign, args.out, args.workers, args.address)
    except ValueError as error:
        print(f'fallback_region: {error}', file=sys.stderr)
        return 2
    flown = results(campaign, rows)
    bounds = [bound(entry) for entry in campaign.laws]
    text = '\n'.join(table(flown, theta_max, campaign) for theta_max in bounds)
    for theta_max in bounds:
        plot(flown, theta_max, campaign,
             os.path.join(args.out, f'fallback_region_{theta_max:g}.png'))
    publish(args.out, 'fallback_region', flown, text, args.page, marker=marker_name(args.out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
