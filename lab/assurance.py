"""Runtime assurance measured: the supervised learned NMPC (`make_controller('koopman_nmpc')`,
the default) against the bare one (`supervisor='none'`) and its fallback flown alone
(`physics_nmpc`), ROS-free from the nine comparison starts.

    python -m lab.assurance [--parts nominal swing robust] [--out lab/results/assurance]

Parts: `nominal`, the shipped settings on the nominal plant (the supervisor should change
nothing); `swing`, `theta_max 0.4` (the bare learned NMPC tumbles from three starts); `robust`,
actuator gain 0.8 and 1.2 with an unmodelled 0.05-tau lag and sensor noise 1e-3 (is a start
slower supervised?). Per run: settle tau, swing, the frontier ratio at the run's swing, the
supervisor's switches and the steps its fallback flew. Writes assurance.md and assurance.json
into --out and the tables into docs/supervisor.md between its markers.
"""

import argparse
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
LAWS = {'bare': ('koopman_nmpc', {'supervisor': 'none'}),
        'supervised': ('koopman_nmpc', {}),
        'fallback alone': ('physics_nmpc', {})}
PAGE = os.path.join('docs', 'supervisor.md')


def fly(label, start, settings, plant=None, steps=2000):
    law_name, options = LAWS[label]
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


def parser():
    p = argparse.ArgumentParser(prog='assurance', description=__doc__.split('\n\n')[0])
    p.add_argument('--parts', nargs='+', default=['nominal', 'swing', 'robust'],
                   choices=('nominal', 'swing', 'robust'))
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
    text = '\n\n'.join(sections) + '\n'
    publish(args.out, 'assurance', rows, text, args.page, marker=marker_name(args.out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
