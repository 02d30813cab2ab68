"""The minimum-time frontier table: recompute it with the project's solver, or show it.

    python -m lab.frontier [--start I ...] [--out PATH]
    python -m lab.frontier --show [PATH]

Starts are indexed in `evaluation.starts.TABULATED_STARTS` (0..10: the comparison, held-out and
swing tuning starts). A recompute solves, per start, the least swing and the minimum time under
every swing bound of min_time.THETA_GRID (lab/min_time.py, needs casadi; 20 s to 6 min a
bound on one core, about an hour for the first nine starts), printing each row as it is done and
writing the table after each start. An existing table at --out keeps its other starts, so a long
recompute can be split with --start. To update the shipped table, point --out at
tsr_koopman_ctrl/evaluation/frontier_table.json.
--show prints a table (default: the shipped one) as markdown.
"""

import argparse
import datetime
import json
import math
import os
import sys

from tsr_koopman_ctrl.evaluation.frontier import TABLE_PATH
from tsr_koopman_ctrl.evaluation.starts import TABULATED_STARTS as STARTS

COMMAND = ('python -m lab.frontier --out '
           'ros2_ws/src/tsr_koopman_ctrl/tsr_koopman_ctrl/evaluation/frontier_table.json'
           ' [--start I ...]')
#: The bounds --show gives a column each (None: unconstrained).
SHOWN_BOUNDS = (1.0, 0.8, 0.6, 0.5, 0.4, 0.3)


def number(value, digits):
    """A finite float rounded for the table; None for NaN or None."""
    if value is None or not math.isfinite(float(value)):
        return None
    return round(float(value), digits)


def record(row, max_defect):
    """A row of `min_time.frontier_table` as the table stores it."""
    result = row['result'] or {}
    return {'theta_max': row['theta_max'], 'T': number(row['T'], 6),
            'swing': number(row['swing'], 6), 'zone_tau': number(row['zone_tau'], 6),
            'success': bool(row['success']), 'solve_s': number(row['solve_s'], 1),
            'intervals': len(result.get('tensions', ())) or None,
            'max_defect': None if max_defect is None else float(f'{max_defect:.2g}'),
            'note': row['note']}


def table_entry(x0, u_max, records, computed, note=None):
    """A start's entry: the bound rows loosest first, and the least-swing row on its own."""
    rows = sorted((r for r in records if r['theta_max'] != 'min'),
                  key=lambda r: -math.inf if r['theta_max'] is None else -r['theta_max'])
    least = next((r for r in records if r['theta_max'] == 'min'), None)
    if least is None:
        least = {'T': None, 'swing': None, 'zone_tau': None, 'success': False, 'solve_s': None,
                 'intervals': None, 'max_defect': None, 'note': 'not computed'}
    entry = {'x0': [float(v) for v in x0], 'u_max': float(u_max), 'computed': computed,
             'rows': rows, 'least_swing': {k: v for k, v in least.items() if k != 'theta_max'}}
    if note:
        entry['note'] = note
    return entry


def provenance(computed, casadi_version):
    """The table's header: who computed it, how, and how to do it again."""
    from lab import min_time
    return {
        'computed': computed,
        'by': "the project's minimum-time solver, lab.min_time",
        'command': COMMAND,
        'problem': 'least T with x(0) = x0, x(T) = 0 (rates included), 0 <= u <= u_max, '
                   '|theta| <= theta_max at every RK4 substep (null: free), l >= 0.001',
        'method': 'direct multiple shooting, free T, u constant per interval, graded first '
                  'intervals, RK4 as tsr_sim.dynamics with substeps per interval; IPOPT from '
                  'LQR closed-loop seeds and the previous bound\'s plan, best converged kept, '
                  'then re-solved on the fine grid; bounds under the least swing not attempted',
        'settings': {
            'grading': list(min_time.GRADING), 'coarse_step': min_time.COARSE_STEP,
            'fine_step': min_time.FINE_STEP,
            'intervals': [min_time.MIN_INTERVALS, min_time.MAX_INTERVALS],
            'max_substep': min_time.MAX_SUBSTEP, 'stiff_fraction': min_time.STIFF_FRACTION,
            'max_substeps': min_time.MAX_SUBSTEPS,
            'ipopt': {k.split('.', 1)[1]: v for k, v in min_time.IPOPT_OPTIONS.items()},
            'guess_weights': [list(w) for w in min_time.TABLE_OPTIONS['guess_weights']],
            'duration_scales': list(min_time.TABLE_OPTIONS['duration_scales']),
            'least_swing_cap': min_time.LEAST_SWING_CAP, 'theta_grid': list(min_time.THETA_GRID),
        },
        'software': {'casadi': casadi_version},
        'fields': 'T, zone_tau (1% zone entry of the plan), solve_s: tau, tau, s; swing: max '
                  '|theta| of the plan; intervals: N; max_defect: largest node mismatch of the '
                  'plan flown through tsr_sim.dynamics.rk4_step',
    }


def recompute(indices, out):
    """Solve the table for the starts `indices`, merging into the table at `out` if any."""
    import casadi
    from lab import min_time
    table = read_table(out) if os.path.exists(out) else {'starts': []}
    today = datetime.date.today().isoformat()
    for i in indices:
        x0 = STARTS[i]

        def progress(row, i=i):
            print(f"start {i} {list(x0)}: theta_max {row['theta_max']}: T {row['T']:.4f}, "
                  f"swing {row['swing']:.4f}, {row['solve_s']:.0f} s {row['note']}", flush=True)

        rows = min_time.frontier_table(x0, progress=progress, **min_time.TABLE_OPTIONS)
        records = [record(r, float(min_time.interval_defects(r['result']).max())
                          if r['success'] else None) for r in rows]
        entry = table_entry(x0, min_time.dynamics.TENSION_LIMIT, records, today)
        kept = [e for e in table['starts'] if [float(v) for v in e['x0']] != entry['x0']]
        order = {tuple(s): k for k, s in enumerate(STARTS)}
        table = {'provenance': provenance(today, casadi.__version__),
                 'starts': sorted(kept + [entry],
                                  key=lambda e: order.get(tuple(e['x0']), len(STARTS)))}
        write_table(table, out)
    return table


def read_table(path):
    try:
        with open(path) as f:
            table = json.load(f)
        if not isinstance(table, dict) or not isinstance(table.get('starts'), list):
            raise ValueError('no "starts" list')
    except (OSError, ValueError) as error:
        raise ValueError(f'{path} is not a frontier table: {error}') from None
    return table


def compact_json(value, level=0):
    """JSON with every container that holds no container (a row, x0) on one line."""
    children = list(value.values()) if isinstance(value, dict) else value
    if not isinstance(value, (dict, list)) or not any(isinstance(c, (dict, list))
                                                      for c in children):
        return json.dumps(value)
    pad, inner = ' ' * level, ' ' * (level + 1)
    if isinstance(value, dict):
        items = [f'{inner}{json.dumps(k)}: {compact_json(v, level + 1)}'
                 for k, v in value.items()]
        return '{\n' + ',\n'.join(items) + f'\n{pad}}}'
    items = [f'{inner}{compact_json(v, level + 1)}' for v in value]
    return '[\n' + ',\n'.join(items) + f'\n{pad}]'


def write_table(table, path):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    temporary = f'{path}.tmp'
    with open(temporary, 'w') as f:
        f.write(compact_json(table) + '\n')
    os.replace(temporary, path)   # a run stopped mid-write leaves the old table whole


def fmt(value, digits=2):
    return '-' if value is None else f'{value:.{digits}f}'


def markdown(table):
    """One line per start: T (tau) at each bound, the least swing, and extra bounds near it."""
    header = ' | '.join(f'{b}' for b in SHOWN_BOUNDS)
    lines = [f'| # | x0 | unconstrained: T (swing) | {header} | least swing | '
             'other bounds: T |', '|---' * (len(SHOWN_BOUNDS) + 5) + '|']
    for index, entry in enumerate(table['starts']):
        rows = {r['theta_max']: r for r in entry['rows']}
        free = rows.get(None)
        cells = [f"{fmt(free['T'])} ({fmt(free['swing'], 3)})"
                 if free and free['success'] else '-']
        for bound in SHOWN_BOUNDS:
            row = rows.get(bound)
            if row is None:
                cells.append('-')
            elif row['success']:
                cells.append(fmt(row['T']))
            else:
                cells.append('infeasible' if row['note'].startswith('infeasible') else 'no solve')
        least = entry['least_swing']
        cells.append(fmt(least['swing'], 3) if least['success'] else '-')
        extra = [f"{b}: {fmt(r['T'])}" for b, r in rows.items()
                 if b is not None and b not in SHOWN_BOUNDS and r['success']]
        cells.append(', '.join(extra) or '-')
        lines.append(f"| {index} | {entry['x0']} | " + ' | '.join(cells) + ' |')
    return '\n'.join(lines) + '\n'


class Parser(argparse.ArgumentParser):
    """argparse with its errors on one line."""

    def error(self, message):
        print(f'frontier: {message}', file=sys.stderr)
        raise SystemExit(2)


def parser():
    p = Parser(prog='frontier', description=__doc__.split('\n\n')[0])
    p.add_argument('--start', type=int, nargs='+', metavar='I',
                   help=f'start indices 0..{len(STARTS) - 1} (default: all)')
    p.add_argument('--out', default=os.path.join('out', 'frontier_table.json'),
                   help='table to write (an existing one keeps its other starts)')
    p.add_argument('--show', nargs='?', const=str(TABLE_PATH), metavar='PATH',
                   help='print a table as markdown (default: the shipped one) and exit')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    try:
        if args.show is not None:
            print(markdown(read_table(args.show)), end='')
            return 0
        indices = args.start if args.start is not None else range(len(STARTS))
        bad = [i for i in indices if not 0 <= i < len(STARTS)]
        if bad:
            raise ValueError(f'no start {bad[0]}: starts are 0..{len(STARTS) - 1} '
                             '(evaluation.starts.TABULATED_STARTS)')
        if os.path.isdir(args.out):
            raise ValueError(f'--out {args.out} is a directory; give a file name')
        if os.path.exists(args.out):
            read_table(args.out)   # fail now, not after an hour of solving
        recompute(list(indices), args.out)
    except ValueError as error:
        print(f'frontier: {error}', file=sys.stderr)
        return 2
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
