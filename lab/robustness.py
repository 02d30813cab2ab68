"""Offset-free control against actuator error, lag and sensor noise: the settle-time grid.

    python -m lab.robustness [--law koopman_mpc linear_lqr] [--out DIR] [--page PAGE]

For each law, bare (observer off) and offset-free (the default), from the comparison starts
and two held-out starts, on the nominal plant and on a tension actuator with gain 0.8, 0.9,
1.1, 1.2 and a 0.05-tau lag, each without and with 1e-3 sensor noise on every component: the
settle time into the 1% zone (judged on the true state) and its ratio to the same law's on the
nominal plant from the same start. ROS-free: `control.closed_loop` runs the simulator's plant.
With --page, the page's tables go into it between the markers named after --out.
"""

import argparse
import os
import sys

from tsr_koopman_ctrl.control import closed_loop, CONTROLLERS, make_controller
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, HELD_OUT_STARTS, run_figures
from tsr_koopman_ctrl import arguments
from lab.report import check_page, marker_name, publish, stamp, write_into_page

STARTS = COMPARISON_STARTS + HELD_OUT_STARTS[:2]
GAINS = (0.8, 0.9, 1.1, 1.2)
LAG = 0.05
NOISE = 1e-3


def cases():
    yield 'nominal', {}
    for noise in (0.0, NOISE):
        for gain in GAINS:
            plant = {'actuator_gain': gain, 'actuator_lag': LAG}
            if noise:
                plant.update(sensor_noise_std=[noise] * 4, seed=7)
            yield f'gain {gain}, lag {LAG}' + (f', noise {noise:g}' if noise else ''), plant


#: The grid is flown without the predictive safety filter, as docs/robustness.md was measured:
#: its certificates do not model the actuator's lag and gain, and on the weak lagging actuator
#: its hand-overs to the slower fallback cost (from the paper's start, gain 0.8 and lag 0.05:
#: 6.18 tau filtered against 3.69 unfiltered).
SAFETY = 'none'


def settle(law, observer, x0, plant, steps):
    import numpy as np
    states, tensions = closed_loop(make_controller(law, observer=observer, safety=SAFETY), x0,
                                   steps, plant=plant)
    figures = run_figures(np.arange(len(states)) * 0.01, states, tensions,
                          halted=len(states) <= steps)
    return figures['settle_tau'], figures['final_state'][2]


def grid(laws, steps):
    rows = []
    for law in laws:
        for observer, label in (({'disturbance': 'none'}, 'bare'), ({}, 'offset-free')):
            # (settle tau, final l - 1) on the nominal plant: the ratios' reference, and the
            # nominal row itself (its final offset is what the table shows if it never settles)
            nominal = {x0: settle(law, observer, x0, {}, steps) for x0 in STARTS}
            for case, plant in cases():
                results = [settle(law, observer, x0, plant, steps) if plant else nominal[x0]
                           for x0 in STARTS]
                rows.append({'law': law, 'control': label, 'case': case, 'starts': [
                    {'x0': list(x0), 'settle_tau': tau, 'final_length_offset': offset,
                     'ratio': None if tau is None or nominal[x0][0] is None
                     else tau / nominal[x0][0]} for x0, (tau, offset) in zip(STARTS, results)]})
                settled = ['-' if r['settle_tau'] is None else f"{r['settle_tau']:.2f}"
                           for r in rows[-1]['starts']]
                print(f"{law} {label} {case}: {', '.join(settled)}", flush=True)
    return rows


def markdown(rows):
    lines = ['Settle tau into the 1% zone (true state) per start '
             f'({", ".join(str(list(x)) for x in STARTS)}); in brackets the ratio to the same '
             'law on the nominal plant; "-" did not settle (final l - 1 given).', '',
             '| law | control | plant | settled | worst ratio | per start |',
             '|---|---|---|---|---|---|']
    for r in rows:
        settled = [s for s in r['starts'] if s['settle_tau'] is not None]
        ratios = [s['ratio'] for s in settled if s['ratio'] is not None]
        cells = ', '.join(f"{s['settle_tau']:.2f} ({s['ratio']:.2f})" if s['settle_tau']
                          is not None and s['ratio'] is not None
                          else f"{s['settle_tau']:.2f}" if s['settle_tau'] is not None
                          else f"- ({s['final_length_offset']:+.3f})" for s in r['starts'])
        worst = f'{max(ratios):.2f}' if ratios else '-'
        lines.append(f"| {r['law']} | {r['control']} | {r['case']} | "
                     f"{len(settled)}/{len(r['starts'])} | {worst} | {cells} |")
    return '\n'.join(lines) + '\n'


def page_tables(rows):
    """The page's view: per law and control, the nominal settle times and how the 48 disturbed
    cases went; then the first law's offset-free ratio per actuator gain and start (no
    noise)."""
    lines = [f'{stamp()}. Settle tau into the 1% zone, judged on the true state; "within '
             '1.2x": of its own nominal settle time from the same start.', '',
             '| law | nominal plant, settle tau per start | disturbed: settled | '
             'disturbed: within 1.2x its nominal | worst ratio to its nominal |',
             '|---|---|---|---|---|']
    for law, control in dict.fromkeys((r['law'], r['control']) for r in rows):
        mine = [r for r in rows if (r['law'], r['control']) == (law, control)]
        nominal = next(r for r in mine if r['case'] == 'nominal')['starts']
        disturbed = [s for r in mine if r['case'] != 'nominal' for s in r['starts']]
        settled = [s for s in disturbed if s['settle_tau'] is not None]
        ratios = [s['ratio'] for s in settled if s['ratio'] is not None]
        label = 'offset-free (default)' if control == 'offset-free' else control
        times = ', '.join('-' if s['settle_tau'] is None else f"{s['settle_tau']:.2f}"
                          for s in nominal)
        lines.append(f'| `{law}`, {label} | {times} | {len(settled)} / {len(disturbed)} | '
                     f'{sum(q <= 1.2 for q in ratios)} | '
                     f"{f'{max(ratios):.2f}' if ratios else '-'} |")
    first = rows[0]['law']
    lines += ['', f'The offset-free `{first}`, ratio to its nominal settle time per start (no '
              'sensor noise; "-": not settled):', '',
              f'| actuator gain (lag {LAG} tau) | '
              + ' | '.join(str(tuple(x)) for x in STARTS) + ' |',
              '|---' * (len(STARTS) + 1) + '|']
    for r in rows:
        if (r['law'], r['control']) == (first, 'offset-free') and r['case'] != 'nominal' \
                and 'noise' not in r['case']:
            gain = r['case'].split(',')[0].split()[1]
            lines.append(f'| {gain} | ' + ' | '.join(
                '-' if s['ratio'] is None else f"{s['ratio']:.2f}" for s in r['starts']) + ' |')
    return '\n'.join(lines) + '\n'


def parser():
    p = argparse.ArgumentParser(prog='robustness', description=__doc__.split('\n\n')[0])
    p.add_argument('--law', nargs='+', default=['koopman_mpc', 'linear_lqr'],
                   choices=sorted(CONTROLLERS))
    p.add_argument('--steps', type=arguments.STEPS, default=2000)
    p.add_argument('--out', default=os.path.join('out', 'robustness'), type=arguments.output_dir)
    p.add_argument('--page', default='', help='a docs page to write the tables into, between '
                   'the markers named after --out (docs/robustness.md has them)')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.page:
        try:
            check_page(args.page, marker_name(args.out))
        except ValueError as error:
            print(f'robustness: {error}', file=sys.stderr)
            return 2
    rows = grid(args.law, args.steps)
    text = markdown(rows)
    publish(args.out, 'robustness', rows, text)
    if args.page:
        write_into_page(args.page, marker_name(args.out), page_tables(rows))
    return 0


if __name__ == '__main__':
    sys.exit(main())
