"""The NMPC's closed-loop figures, both maps: what docs/nmpc.md reports.

    python lab/bench/nmpc_figures.py nominal    [--law physics_nmpc koopman_nmpc] [--bare]
    python lab/bench/nmpc_figures.py swing0.4   (theta_max 0.4)
    python lab/bench/nmpc_figures.py robustness (actuator gain 0.8..1.2, 0.05-tau lag, 1e-3 noise)
    ... [--steps 2000] [--set law.name=value ...] [--starts 0,3] [--out FILE.json]
        [--supervised] [--page docs/nmpc.md]

`nominal` and `swing0.4`: from the nine comparison and held-out starts on the nominal plant:
settle tau, swing, frontier ratio at the run's own swing (and, for swing0.4, to the 0.4-rad
frontier), fallbacks, compute time per step (median, p99; the first step, the cold start, left
out) beside the yardstick (one scalar numpy RK4 plant step of 20 substeps,
lab/bench/yardstick.py), timed before and after every run.
`robustness`: offset-free (the default observer) from lab/robustness.py's six starts on the
plant with actuator gain g in (0.8, 0.9, 1.1, 1.2), a 0.05-tau actuator lag and 1e-3 sensor
noise (seed 7), and on the nominal plant: the settle tau and its ratio to the nominal one.
The law alone (no runtime-assurance supervisor unless --supervised), offset-free (the default
observer) unless --bare. With --page (and --out), the suite's tables go into the page between
the markers named after --out's file name (nmpc_nominal for .../nmpc_nominal.json).
One process, single-threaded numpy: run with OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1.
"""

import argparse
import json
import os
import sys

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.control.registry import parse_assignments
from tsr_koopman_ctrl.evaluation import (COMPARISON_STARTS, frontier_tau, HELD_OUT_STARTS,
                                         run_figures)

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import marker  # noqa: E402
from lab.bench.yardstick import seconds as yardstick  # noqa: E402
from tsr_koopman_ctrl.evaluation.figures import SWING_TOLERANCE  # noqa: E402
from lab.report import check_page, stamp, write_into_page  # noqa: E402

STARTS = COMPARISON_STARTS + HELD_OUT_STARTS
ROBUSTNESS_STARTS = COMPARISON_STARTS + HELD_OUT_STARTS[:2]   # lab/robustness.py's
GAINS = (0.8, 0.9, 1.1, 1.2)


def run(law_name, settings, start, steps, bare, plant=None, supervised=False):
    observer = {'disturbance': 'none'} if bare else None
    law = make_controller(law_name, observer=observer,
                          supervisor=None if supervised else 'none', **settings)
    seconds = []
    before = yardstick()
    states, tensions = closed_loop(law, start, steps, plant=plant, compute_seconds=seconds)
    after = yardstick()
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions,
                          start=start, halted=len(states) <= steps)
    ms = np.array(seconds[1:]) * 1e3
    yard = 0.5 * (before + after) * 1e3
    return {'law': law_name, 'x0': list(start), 'settings': settings, 'bare': bare,
            'plant': plant, 'settle_tau': figures['settle_tau'], 'swing': figures['swing'],
            'frontier_ratio': figures['frontier_ratio'], 'fallbacks': law.fallbacks,
            'final_state': figures['final_state'], 'cold_ms': seconds[0] * 1e3,
            'median_ms': float(np.median(ms)), 'p99_ms': float(np.percentile(ms, 99)),
            'max_ms': float(ms.max()), 'yardstick_ms': yard,
            'median_x_yardstick': float(np.median(ms)) / yard,
            'p99_x_yardstick': float(np.percentile(ms, 99)) / yard}


def fmt(value, spec='.3f'):
    return '-' if value is None else format(value, spec)


def start_label(start):
    return '(' + ', '.join(f'{v:g}' for v in start) + ')'


def by_start(rows, laws):
    """{start: {law: row}} in the order the runs were made (nominal plant only)."""
    table = {}
    for row in rows:
        if row['plant'] is None:
            table.setdefault(tuple(row['x0']), {})[row['law']] = row
    return {start: cells for start, cells in table.items() if all(law in cells for law in laws)}


def span(values, spec):
    values = [v for v in values if v is not None]
    return '-' if not values else f'{min(values):{spec}}..{max(values):{spec}}'


def nominal_tables(rows, laws):
    lines = ['| law | median ms | p99 ms | median x yardstick | p99 x yardstick |',
             '|---|---|---|---|---|']
    for law in laws:
        own = [r for r in rows if r['law'] == law]
        lines.append(f"| {law} | {span([r['median_ms'] for r in own], '.2f')} | "
                     f"{span([r['p99_ms'] for r in own], '.2f')} | "
                     f"{span([r['median_x_yardstick'] for r in own], '.1f')} | "
                     f"{span([r['p99_x_yardstick'] for r in own], '.1f')} |")
    lines += ['', 'Settle tau / swing [rad] / **ratio to the frontier at that swing** / fallbacks'
              + (f'; the settle time of `{laws[1]}` over `{laws[0]}`' if len(laws) == 2
                 else '') + ':', '',
              '| start | ' + ' | '.join(f'`{law}`' for law in laws)
              + (f' | {laws[1]} / {laws[0]} |' if len(laws) == 2 else ' |'),
              '|---' * (1 + len(laws) + (len(laws) == 2)) + '|']
    for start, cells in by_start(rows, laws).items():
        line = f'| {start_label(start)} | ' + ' | '.join(
            f"{fmt(cells[law]['settle_tau'], '.2f')} / {cells[law]['swing']:.3f} / "
            f"**{fmt(cells[law]['frontier_ratio'])}** / {cells[law]['fallbacks']}"
            for law in laws)
        if len(laws) == 2:
            first, second = (cells[law]['settle_tau'] for law in laws)
            line += f" | {fmt(None if None in (first, second) else second / first)}"
        lines.append(line + ' |')
    return lines


def swing_tables(rows, laws, bound=0.4):
    lines = [f'Settle tau / swing [rad] / **ratio to the {bound}-rad frontier** where the swing '
             f'stayed within {bound} (+ {SWING_TOLERANCE}); else how it did not:', '',
             '| start | ' + ' | '.join(f'`{law}`' for law in laws) + ' |',
             '|---' * (1 + len(laws)) + '|']
    held, table = {law: 0 for law in laws}, by_start(rows, laws)
    for start, cells in table.items():
        parts = []
        for law in laws:
            r = cells[law]
            if r['swing'] <= bound + SWING_TOLERANCE and r['settle_tau'] is not None:
                held[law] += 1
                parts.append(f"{r['settle_tau']:.2f} / {r['swing']:.3f} / "
                             f"**{fmt(r['ratio_to_04_frontier'])}**")
            else:
                outcome = ('not settled' if r['settle_tau'] is None
                           else f"settled {r['settle_tau']:.2f}")
                plural = '' if r['fallbacks'] == 1 else 's'
                parts.append(f"**not held**: swing {r['swing']:.2f}, {outcome}, "
                             f"{r['fallbacks']} fallback{plural}")
        lines.append(f'| {start_label(start)} | ' + ' | '.join(parts) + ' |')
    lines += ['', 'Held: ' + ', '.join(f'`{law}` {held[law]} of {len(table)}' for law in laws)
              + '.']
    return lines


def robustness_tables(rows, laws, gains):
    lines = ['Settle tau (ratio to the same law\'s nominal settle time):', '',
             '| start | law | nominal | ' + ' | '.join(f'g {g:g}' for g in gains) + ' |',
             '|---' * (3 + len(gains)) + '|']
    within = {law: [0, 0] for law in laws}
    runs = {}
    for row in rows:
        gain = None if row['plant'] is None else row['plant']['actuator_gain']
        runs[(tuple(row['x0']), row['law'], gain)] = row
    starts = list(dict.fromkeys(tuple(row['x0']) for row in rows))
    for start in starts:
        for law in laws:
            nominal = runs.get((start, law, None))
            if nominal is None:
                continue
            cells = []
            for g in gains:
                r = runs[(start, law, g)]
                ratio = r['ratio_to_nominal']
                within[law][1] += 1
                within[law][0] += ratio is not None and ratio <= 1.2
                cells.append('not settled' if r['settle_tau'] is None
                             else f"{r['settle_tau']:.2f} ({ratio:.2f})")
            label = start_label(start) if law == laws[0] else ''
            lines.append(f"| {label} | {law} | {fmt(nominal['settle_tau'], '.2f')} | "
                         + ' | '.join(cells) + ' |')
    settled = sum(r['settle_tau'] is not None for r in rows)
    lines += ['', f'{settled} of {len(rows)} runs settle; within 1.2x nominal: '
              + ', '.join(f'`{law}` {a} of {b}' for law, (a, b) in within.items()) + '.']
    return lines


def page_text(suite, rows, laws, steps, bare, supervised, gains):
    what = ('under the supervisor' if supervised else 'the law alone (no supervisor)') + ', ' + (
        'bare (no observer)' if bare else 'offset-free')
    head = [f'{stamp()}; {what}, {steps} steps, single-threaded.', '']
    if suite == 'nominal':
        return '\n'.join(head + nominal_tables(rows, laws)) + '\n'
    if suite == 'swing0.4':
        return '\n'.join(head + swing_tables(rows, laws)) + '\n'
    return '\n'.join(head + robustness_tables(rows, laws, gains)) + '\n'


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('suite', choices=('nominal', 'swing0.4', 'robustness'))
    parser.add_argument('--law', nargs='+', default=['physics_nmpc', 'koopman_nmpc'])
    parser.add_argument('--steps', type=int, default=2000)
    parser.add_argument('--bare', action='store_true', help='no offset-free observer')
    parser.add_argument('--set', action='append', default=[], metavar='LAW.NAME=VALUE')
    parser.add_argument('--starts', help='indices into the suite\'s starts, e.g. 0,3')
    parser.add_argument('--gains', help='robustness: actuator gains, e.g. 0.9,1.1')
    parser.add_argument('--out')
    parser.add_argument('--supervised', action='store_true',
                        help='fly each learned law under its runtime-assurance supervisor')
    parser.add_argument('--page', default='', help='a docs page to write the tables into, '
                        'between the markers named after --out\'s file name (needs --out)')
    args = parser.parse_args(argv)
    if args.page:
        try:
            if not args.out:
                raise ValueError('--page needs --out (the markers are named after it)')
            check_page(args.page, marker(args.out))
        except ValueError as error:
            parser.exit(2, f'nmpc_figures: {error}\n')
    overrides = {law: {} for law in args.law}
    for law, values in parse_assignments(args.set).items():   # deploy's --set, parsed alike
        if law in overrides:
            overrides[law].update(values)
    if args.suite == 'swing0.4':
        for law in args.law:
            overrides[law].setdefault('theta_max', 0.4)
    starts = ROBUSTNESS_STARTS if args.suite == 'robustness' else STARTS
    if args.starts:
        starts = [starts[int(i)] for i in args.starts.split(',')]
    gains = (tuple(float(g) for g in args.gains.split(',')) if args.gains else GAINS)
    rows = []
    for law in args.law:
        for start in starts:
            plants = [None]
            if args.suite == 'robustness':
                plants += [{'actuator_gain': g, 'actuator_lag': 0.05,
                            'sensor_noise_std': [1e-3] * 4, 'seed': 7} for g in gains]
            nominal = None
            for plant in plants:
                row = run(law, overrides[law], start, args.steps, args.bare, plant,
                          args.supervised)
                if plant is None:
                    nominal = row['settle_tau']
                row['nominal_settle_tau'] = nominal
                row['ratio_to_nominal'] = (None if nominal is None or row['settle_tau'] is None
                                           else row['settle_tau'] / nominal)
                if args.suite == 'swing0.4':
                    bound = frontier_tau(start, 0.4)
                    row['frontier_04_tau'] = bound
                    row['ratio_to_04_frontier'] = (None if bound is None or row['settle_tau']
                                                   is None else row['settle_tau'] / bound)
                rows.append(row)
                gain = '-' if plant is None else plant['actuator_gain']
                print(f"{law} {list(start)} gain {gain}: settle {fmt(row['settle_tau'], '.2f')} "
                      f"swing {row['swing']:.3f} ratio {fmt(row['frontier_ratio'])} "
                      f"to04 {fmt(row.get('ratio_to_04_frontier'))} "
                      f"to_nominal {fmt(row['ratio_to_nominal'])} fb {row['fallbacks']} "
                      f"ms {row['median_ms']:.2f}/{row['p99_ms']:.2f} "
                      f"yard {row['yardstick_ms']:.3f} "
                      f"(x{row['median_x_yardstick']:.1f}/x{row['p99_x_yardstick']:.1f})",
                      flush=True)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, 'w') as handle:
            json.dump({'suite': args.suite, 'steps': args.steps, 'bare': args.bare,
                       'supervised': args.supervised, 'rows': rows}, handle, indent=1)
    if args.page:
        text = page_text(args.suite, rows, args.law, args.steps, args.bare, args.supervised,
                         gains)
        write_into_page(args.page, marker(args.out), text)
        print(text)


if __name__ == '__main__':
    main()
