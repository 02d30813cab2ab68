"""Runtime assurance measured: the supervised learned NMPC (`koopman_nmpc` without its safety
filter) against the bare one (no supervisor) and its fallback flown alone (`physics_nmpc`),
ROS-free from the nine comparison starts.

    python -m lab.assurance [--parts nominal swing robust] [--out lab/results/assurance]
    python -m lab.assurance --parts monitor \
        --out lab/results/assurance_monitor

Each part is a campaign spec under lab/campaigns/assurance/, flown through the product's
campaign API (`tsr_koopman_ctrl.campaign`) into <out>/<part> (resumed where rows exist):
`nominal`, the shipped settings on the nominal plant (the supervisor should change nothing);
`swing`, `theta_max 0.4` (the bare learned NMPC tumbles from three starts); `robust`, actuator
gain 0.8 and 1.2 with an unmodelled 0.05-tau lag and sensor noise 1e-3 (is a start slower
supervised?); `monitor`, the robust part's runs under other monitor settings, beside the bare
law from starts moved by a nudge far below any sensor's resolution (`monitor_nudged`): does
one leave no start slower than bare? Per run: settle tau, swing, the frontier ratio at the
run's swing, the supervisor's switches. Writes assurance.md and assurance.json into --out and
the tables into docs/supervisor.md between the markers named after --out.
"""

import argparse
import math
import os
import sys

import numpy as np
from tsr_sim import dynamics

from lab import campaigns
from lab.report import check_page, marker_name, publish

SPECS = {part: campaigns.spec_path(os.path.join('assurance', f'{part}.yaml'))
         for part in ('nominal', 'swing', 'robust', 'monitor', 'monitor_nudged')}
PARTS = ('nominal', 'swing', 'robust', 'monitor')
PAGE = os.path.join('docs', 'supervisor.md')
#: Settle times closer than half a step are the same.
TIE = 0.5 * dynamics.PAPER_STEP
CELLS = 'each cell: settle tau (swing [rad], ratio to the minimum time at that swing)'


def fly(part, out, steps=None, runs=None, workers=None, address=None):
    """(campaign, rows) of one part's spec, flown into <out>/<part> (resumed if begun)."""
    from tsr_koopman_ctrl.campaign import load_spec
    campaign = load_spec(SPECS[part], steps=steps, runs=runs)
    return campaign, campaigns.fly(campaign, os.path.join(out, part), workers, address)


def heading(entry):
    """A law's name on the page: its supervisor settings where it sets some, else its label
    (underscores as spaces)."""
    settings = {k: v for k, v in entry.settings.get('supervisor', {}).items() if k != 'fallback'}
    return ', '.join(f'{k} {v}' for k, v in settings.items()) or entry.label.replace('_', ' ')


def results(campaign, rows, part, starts=None):
    """The rows as the page reads them, in the spec's order (case, start, law): law (its
    heading), start (of `starts` if given, else the spec's, by the run's start index),
    settle_tau (None: not settled), swing, ratio, halted, switches, part, plant (its case)."""
    starts = starts or campaign.start_list
    headings = {entry.label: heading(entry) for entry in campaign.laws}
    order = [entry.label for entry in campaign.laws]

    def value(number):
        return None if math.isnan(number) else float(number)
    flown = []
    for row in rows.to_dict('records'):
        start, case = campaign.position(int(row['run']))
        flown.append(((case, start, order.index(row['law'])), {
            'law': headings[row['law']], 'start': list(starts[start]),
            'settle_tau': value(row['settle_tau']), 'swing': value(row['swing']),
            'ratio': value(row['frontier_ratio']), 'halted': bool(row['halted']),
            'switches': int(row['switches']), 'part': part, 'plant': row.get('case')}))
    return [result for _, result in sorted(flown, key=lambda pair: pair[0])]


def cell(row):
    if row['settle_tau'] is None:
        return 'tumbled' if row['halted'] else 'not settled'
    ratio = '' if row['ratio'] is None else f", {row['ratio']:.3f}x"
    return f"{row['settle_tau']:.2f} ({row['swing']:.3f}{ratio})"


def part_table(campaign, rows):
    """One markdown table of a part's `rows` (`results`): a line per start, a column per law,
    then the supervised law's switches."""
    labels = [heading(entry) for entry in campaign.laws]
    lines = ['| start | ' + ' | '.join(labels) + ' | switches |',
             '|---' * (len(labels) + 2) + '|']
    for start in dict.fromkeys(tuple(row['start']) for row in rows):
        mine = {row['law']: row for row in rows if tuple(row['start']) == start}
        lines.append(f'| {list(start)} | '
                     + ' | '.join(cell(mine[label]) if label in mine else '-' for label in labels)
                     + f" | {mine.get('supervised', {}).get('switches', '-')} |")
    return '\n'.join(lines)


def nudge(monitor, nudged):
    """How far the yardstick's starts are moved in theta from the monitor part's; ValueError
    unless the two specs differ in that alone (and their laws)."""
    moved = np.subtract(nudged.start_list, monitor.start_list) if len(
        nudged.start_list) == len(monitor.start_list) else None
    if moved is None or np.any(moved[:, 1:]) or [c.label for c in nudged.cases] != [
            c.label for c in monitor.cases] or nudged.seed != monitor.seed:
        raise ValueError(f"{SPECS['monitor_nudged']}: must be {SPECS['monitor']}'s starts, in "
                         'its order, moved in theta alone, with its cases and seed')
    return float(np.max(np.abs(moved[:, 0])))


def monitor_rows(monitor, rows, nudged, nudged_rows):
    """The monitor part's rows, the yardstick's first (law 'bare, theta0 + <nudge> rad', at
    the start it was moved from)."""
    moved = results(nudged, nudged_rows, 'monitor', starts=monitor.start_list)
    for row in moved:
        row['law'] = f'bare, theta0 + {nudge(monitor, nudged):g} rad'
    return moved + results(monitor, rows, 'monitor')


def monitor_table(rows):
    """One markdown table of the monitor part's `rows` (law, plant, start, settle_tau,
    switches): per setting and plant, the runs slower than the bare law's from the same start
    by more than TIE (by up to how much), the runs faster, the summed settle and switches."""
    plants = list(dict.fromkeys(row['plant'] for row in rows))
    bare = {(row['plant'], tuple(row['start'])): row['settle_tau'] for row in rows
            if row['law'] == 'bare'}
    lines = ['| monitor | ' + ' | '.join(f'{plant}: slower than bare (by up to)'
                                         for plant in plants)
             + ' | faster than bare (by up to) | settle tau, all runs | switches |',
             '|---' * (len(plants) + 4) + '|']
    labels = dict.fromkeys(row['law'] for row in rows if row['law'] != 'bare')
    for label in labels:
        mine = [row for row in rows if row['law'] == label]
        change = []     # (plant, settle tau - bare's, ratio - 1); not settled: +-inf
        for row in mine:
            reference = bare[row['plant'], tuple(row['start'])]
            if row['settle_tau'] is None and reference is None:
                change.append((row['plant'], 0.0, 0.0))      # neither settled: the same
            elif row['settle_tau'] is None or reference is None:
                unsettled = np.inf if row['settle_tau'] is None else -np.inf
                change.append((row['plant'], unsettled, unsettled))
            else:
                change.append((row['plant'], row['settle_tau'] - reference,
                               row['settle_tau'] / reference - 1.0))

        def counted(values, unsettled):
            if not values:
                return '0'
            worst = max(values)
            lost = sum(value == np.inf for value in values)
            return f"{len(values)} ({f'{lost} {unsettled}' if lost else f'{worst:.1%}'})"
        slower = [counted([r for p, d, r in change if p == plant and d > TIE], 'not settled')
                  for plant in plants]
        faster = counted([-r for _, d, r in change if d < -TIE], 'where bare did not settle')
        lines.append(f'| {label} | ' + ' | '.join(slower) + f' | {faster} | '
                     f"{sum(row['settle_tau'] or np.inf for row in mine):.2f} | "
                     f"{sum(row['switches'] for row in mine)} |")
    lines.append(f"| bare | {' | '.join('-' for _ in plants)} | - | "
                 f"{sum(tau or np.inf for tau in bare.values()):.2f} | - |")
    return '\n'.join(lines)


def parser():
    p = argparse.ArgumentParser(prog='assurance', description=__doc__.split('\n\n')[0])
    p.add_argument('--parts', nargs='+', default=['nominal', 'swing', 'robust'], choices=PARTS)
    p.add_argument('--steps', type=int, help="steps per run (default: the specs', 2000)")
    p.add_argument('--runs', type=int, help="the first N runs of each part (default: all)")
    campaigns.add_engine_options(p)
    p.add_argument('--out', default=os.path.join('lab', 'results', 'assurance'))
    p.add_argument('--page', default=PAGE)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    engine = {'steps': args.steps, 'runs': args.runs, 'workers': args.workers,
              'address': args.address}
    rows, sections = [], []
    try:
        if args.page:
            check_page(args.page, marker_name(args.out))
        flown = {part: fly(part, args.out, **engine) for part in PARTS if part in args.parts}
        if 'monitor' in args.parts:
            flown['monitor_nudged'] = fly('monitor_nudged', args.out, **engine)
            nudge(flown['monitor'][0], flown['monitor_nudged'][0])
    except ValueError as error:
        print(f'assurance: {error}', file=sys.stderr)
        return 2
    titles = {'nominal': f'Nominal plant, shipped settings ({CELLS})',
              'swing': f'Swing bound 0.4 rad (`theta_max 0.4`; {CELLS})'}
    for part in ('nominal', 'swing'):
        if part in flown:
            mine = results(*flown[part], part)
            rows += mine
            sections.append(f'{titles[part]}:\n\n' + part_table(flown[part][0], mine))
    if 'robust' in flown:
        campaign, part_rows = flown['robust']
        for case in campaign.cases:
            mine = [row for row in results(campaign, part_rows, case.label)
                    if row['plant'] == case.label]
            if not mine:        # a case beyond --runs
                continue
            rows += mine
            sections.append(f'{case.label} ({CELLS}):\n\n' + part_table(campaign, mine))
    if 'monitor' in flown:
        mine = monitor_rows(*flown['monitor'], *flown['monitor_nudged'])
        rows += mine
        starts = len(flown['monitor'][0].start_list)
        sections.append('The robust part under other monitor settings (runs of '
                        f'{starts} starts per plant; a run is slower or faster than bare '
                        f'when its settle time differs by more than half a step):\n\n'
                        + monitor_table(mine))
    text = '\n\n'.join(sections) + '\n'
    publish(args.out, 'assurance', rows, text, args.page, marker=marker_name(args.out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
