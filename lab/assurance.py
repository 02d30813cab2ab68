"""Runtime assurance measured: the supervised learned NMPC (`make_controller('koopman_nmpc',
safety='none')`, the default without its safety filter) against the bare one
(`supervisor='none'`) and its fallback flown alone
(`physics_nmpc`), ROS-free from the nine comparison starts.

    python -m lab.assurance [--parts nominal swing robust] [--out lab/results/assurance]
    python -m lab.assurance --parts monitor \
        --out lab/results/assurance_monitor

Parts: `nominal`, the shipped settings on the nominal plant (the supervisor should change
nothing); `swing`, `theta_max 0.4` (the bare learned NMPC tumbles from three starts); `robust`,
actuator gain 0.8 and 1.2 with an unmodelled 0.05-tau lag and sensor noise 1e-3 (is a start
slower supervised?); `monitor`, the robust part's runs under other monitor settings
(`MONITOR_VARIANTS`, in --workers processes): does one leave no start slower than bare? Per
run: settle tau, swing, the frontier ratio at the run's swing, the supervisor's switches and
the steps its fallback flew. Writes assurance.md and assurance.json into --out and the tables
into docs/supervisor.md between the markers named after --out.
"""

import argparse
import concurrent.futures
import os
import sys

import numpy as np
from tsr_sim import dynamics

from lab.report import check_page, marker_name, publish
from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, HELD_OUT_STARTS, run_figures

STARTS = COMPARISON_STARTS + HELD_OUT_STARTS
#: The variants of the `robust` part (the robustness grid's actuator cases, docs/robustness.md).
ROBUST_PLANTS = {f'gain {gain}, lag 0.05, noise 1e-3': {
    'actuator_gain': gain, 'actuator_lag': 0.05, 'sensor_noise_std': [1e-3] * 4}
    for gain in (0.8, 1.2)}
#: The laws each part flies: (label, law, make_controller options).
LAWS = {'bare': ('koopman_nmpc', {'supervisor': 'none', 'safety': 'none'}),
        'supervised': ('koopman_nmpc', {'safety': 'none'}),
        'fallback alone': ('physics_nmpc', {})}
#: The monitor settings the `monitor` part flies beside the shipped ones (label: supervisor
#: settings): a quicker or slower hand-back, a fault rule that needs three faults.
MONITOR_VARIANTS = {'shipped': {}, 'takeback_steps 5': {'takeback_steps': 5},
                    'takeback_steps 10': {'takeback_steps': 10},
                    'takeback_steps 40': {'takeback_steps': 40},
                    'fault_count 3, fault_window 3': {'fault_count': 3, 'fault_window': 3}}
#: The `monitor` part's yardstick: the bare law from each start moved by this much in theta
#: [rad], far below any sensor's resolution. How far its settle times move is how far a run
#: moves for no reason a monitor could see.
NUDGE = 1e-9
NUDGED = f'bare, theta0 + {NUDGE:g} rad'
PAGE = os.path.join('docs', 'supervisor.md')
#: Settle times closer than half a step are the same.
TIE = 0.5 * dynamics.PAPER_STEP


def fly(label, start, settings, plant=None, steps=2000):
    law_name, options = LAWS.get(label) or ('koopman_nmpc',
                                            {'supervisor': MONITOR_VARIANTS[label],
                                             'safety': 'none'})
    law = make_controller(law_name, **options, **settings)
    states, tensions = closed_loop(law, start, steps, plant=plant)
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions,
                          start=start, halted=len(states) <= steps)
    return {'law': label, 'start': list(start), 'settle_tau': figures['settle_tau'],
            'swing': figures['swing'], 'ratio': figures['frontier_ratio'],
            'halted': figures['halted'], 'switches': law.switches}


def cell(row):
    if row['settle_tau'] is None:
        return 'tumbled' if row['halted'] else 'not settled'
    ratio = '' if row['ratio'] is None else f", {row['ratio']:.3f}x"
    return f"{row['settle_tau']:.2f} ({row['swing']:.3f}{ratio})"


def part(name, settings, plant, labels, rows):
    """Fly `labels` from every start; one markdown table."""
    lines = ['| start | ' + ' | '.join(labels) + ' | switches |',
             '|---' * (len(labels) + 2) + '|']
    for start in STARTS:
        mine = {label: fly(label, start, settings, plant) for label in labels}
        for label, row in mine.items():
            rows.append({**row, 'part': name})
        lines.append(f'| {list(start)} | ' + ' | '.join(cell(mine[label]) for label in labels)
                     + f" | {mine.get('supervised', {}).get('switches', '-')} |")
        print(f'{name} {list(start)}: ' + ', '.join(f'{k} {cell(v)}' for k, v in mine.items()),
              flush=True)
    return '\n'.join(lines)


def monitor_part(workers, rows):
    """The robust part's runs, bare, bare from a nudged start (NUDGE) and under each of
    MONITOR_VARIANTS, in `workers` processes, appended to `rows`; their table
    (`monitor_table`)."""
    nudge = np.array([NUDGE, 0.0, 0.0, 0.0])
    runs = [(label, start, plant) for plant in ROBUST_PLANTS.values() for start in STARTS
            for label in ['bare', NUDGED, *MONITOR_VARIANTS]]
    jobs = [('bare', list(np.add(start, nudge)), {}, plant) if label == NUDGED
            else (label, start, {}, plant) for label, start, plant in runs]
    with concurrent.futures.ProcessPoolExecutor(workers) as pool:
        flown = list(pool.map(fly, *zip(*jobs)))
    for (label, start, plant), row in zip(runs, flown):
        row.update(law=label, start=list(start), part='monitor',
                   plant=next(k for k, v in ROBUST_PLANTS.items() if v is plant))
        rows.append(row)
    return monitor_table([row for row in rows if row['part'] == 'monitor'])


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
    p.add_argument('--parts', nargs='+', default=['nominal', 'swing', 'robust'],
                   choices=('nominal', 'swing', 'robust', 'monitor'))
    p.add_argument('--workers', type=int, default=2,
                   help='processes the monitor part flies in (default 2)')
    p.add_argument('--out', default=os.path.join('lab', 'results', 'assurance'))
    p.add_argument('--page', default=PAGE)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.page:
        try:
            check_page(args.page, marker_name(args.out))
        except ValueError as error:
            print(f'assurance: {error}', file=sys.stderr)
            return 2
    rows, sections = [], []
    cells = 'each cell: settle tau (swing [rad], ratio to the minimum time at that swing)'
    if 'nominal' in args.parts:
        sections.append('Nominal plant, shipped settings (' + cells + '):\n\n'
                        + part('nominal', {}, None, ['bare', 'supervised'], rows))
    if 'swing' in args.parts:
        sections.append('Swing bound 0.4 rad (`theta_max 0.4`; ' + cells + '):\n\n'
                        + part('swing', {'theta_max': 0.4}, None,
                               ['bare', 'supervised', 'fallback alone'], rows))
    if 'robust' in args.parts:
        for label, plant in ROBUST_PLANTS.items():
            sections.append(f'{label} ({cells}):\n\n'
                            + part(label, {}, plant, ['bare', 'supervised'], rows))
    if 'monitor' in args.parts:
        sections.append('The robust part under other monitor settings (runs of '
                        f'{len(STARTS)} starts per plant; a run is slower or faster than bare '
                        f'when its settle time differs by more than half a step):\n\n'
                        + monitor_part(args.workers, rows))
    text = '\n\n'.join(sections) + '\n'
    publish(args.out, 'assurance', rows, text, args.page, marker=marker_name(args.out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
