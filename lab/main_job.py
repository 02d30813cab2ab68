"""The README's headline: the main job's law and the paper's Koopman-LQR, each deployed over
DDS (simulator, controller, recorder as three processes) from the paper's start, every figure
read back from its bag.

    python -m lab.main_job [--law koopman_nmpc koopman_lqr] [--out lab/results/main_job]
        [--page README.md]

Writes main_job.md (the deployment table), main_job.json and main_job.png (both runs on one
plot) into --out, the bags into --out/bags; with --page, the headline table into the page
between its markers and the plot to docs/figures/main_job.png beside it.
"""

import argparse
import json
import os
import sys

from lab.report import check_page, copy_figure, marker_name, stamp, write_into_page
from tsr_koopman_ctrl import arguments
from tsr_koopman_ctrl.control.registry import CONTROLLERS, DEFAULT_LAW
from tsr_koopman_ctrl.deployment import COLUMNS, Deployment, DeploymentError, summary_table
from tsr_koopman_ctrl.evaluation.plots import plot_deployments


def parser():
    p = argparse.ArgumentParser(prog='main_job', description=__doc__.split('\n\n')[0])
    p.add_argument('--law', nargs='+', default=[DEFAULT_LAW, 'koopman_lqr'],
                   choices=sorted(CONTROLLERS),
                   help=f'the laws, each deployed with its defaults (default {DEFAULT_LAW} '
                   'and the paper\'s koopman_lqr)')
    p.add_argument('--steps', type=arguments.STEPS, default=2000)
    p.add_argument('--out', default='lab/results/main_job')
    p.add_argument('--page', default='', help='a page to write the headline into, between '
                   'the markers named after --out (README.md has them); the plot goes to '
                   'docs/figures/main_job.png beside it')
    p.add_argument('--namespace', help="the nodes' ROS namespace (default: the root; every "
                   'deployment has a DDS domain of its own)')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    rows, curves = [], {}
    try:
        if args.page:
            check_page(args.page, marker_name(args.out))
    except ValueError as error:
        print(f'main_job: {error}', file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    try:
        for law in args.law:
            run = Deployment(law, steps=args.steps, bags=os.path.join(args.out, 'bags'),
                             logs=os.path.join(args.out, 'logs', law), progress=False,
                             namespace=args.namespace).run()
            rows.append(run.figures)
            curves[law] = (run.loop.tau, run.loop.x, run.loop.u[:-1])
            settle, ratio = run.figures['settle_tau'], run.figures['frontier_ratio']
            print(f'{law}: settle tau {"-" if settle is None else f"{settle:.2f}"}, ratio '
                  f'{"-" if ratio is None else f"{ratio:.3f}"}', flush=True)
    except DeploymentError as error:
        print(f'main_job: {error}', file=sys.stderr)
        return 1
    table = summary_table(rows)
    with open(os.path.join(args.out, 'main_job.md'), 'w') as f:
        f.write(table + '\n')
    with open(os.path.join(args.out, 'main_job.json'), 'w') as f:
        json.dump(rows, f, indent=1, default=str)
    plot_deployments(curves, os.path.join(args.out, 'main_job.png'),
                     title='Deployed over DDS from the paper\'s start')
    if args.page:
        write_into_page(args.page, marker_name(args.out), headline(rows))
        copy_figure(args.page, os.path.join(args.out, 'main_job.png'), FIGURE)
    print(table)
    return 0


#: Where the README's plot lives, from the page's folder.
FIGURE = os.path.join('docs', 'figures', 'main_job.png')
#: How the headline names the laws it knows.
ROLES = {DEFAULT_LAW: 'main job', 'koopman_lqr': "the paper's"}


#: The headline's columns: some of deploy's table (`deployment.COLUMNS`), by the same names.
HEADLINE_COLUMNS = ('law', 'settle tau (1% zone)', 'swing [rad]', 'l overshoot', 'max u',
                    'compute median / p99 [ms]', 'minimum time at that swing [tau]', 'ratio')


def headline(rows):
    """The README's table: one row per run, deploy's cells of HEADLINE_COLUMNS, the main job's
    settle time and every ratio bold."""
    lines = [f"Deployed over DDS from the paper's start ({stamp()}; every figure read back "
             'from the bags):', '',
             '| ' + ' | '.join(HEADLINE_COLUMNS) + ' |', '|' + '---|' * len(HEADLINE_COLUMNS)]
    for r in rows:
        law = r['controller']
        cells = {column: COLUMNS[column](r) for column in HEADLINE_COLUMNS}
        cells['law'] = f'`{law}`' + (f' ({ROLES[law]})' if law in ROLES else '')
        if law == DEFAULT_LAW:
            cells['settle tau (1% zone)'] = f"**{cells['settle tau (1% zone)']}**"
        cells['ratio'] = f"**{cells['ratio']}**"
        lines.append('| ' + ' | '.join(cells.values()) + ' |')
    switches = sum(r.get('supervisor_switches') or 0 for r in rows)
    corrected = sum(r.get('safety_corrections') or 0 for r in rows)
    lines += ['', f'The runtime-assurance supervisor handed over {switches} times in these runs, '
              f'and the safety filter corrected {corrected} steps.']
    return '\n'.join(lines) + '\n'


if __name__ == '__main__':
    sys.exit(main())
