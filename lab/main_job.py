"""The README's headline: the main job's law and the paper's Koopman-LQR, each deployed over
DDS (simulator, controller, recorder as three processes) from the paper's start, every figure
read back from its bag.

    python -m lab.main_job [--law koopman_nmpc koopman_lqr] [--out lab/results/main_job]

Writes main_job.md (the deployment table), main_job.json and main_job.png (both runs on one
plot) into --out; the bags go to --out/bags.
"""

import argparse
import json
import os
import sys

from tsr_koopman_ctrl import arguments
from tsr_koopman_ctrl.control.registry import CONTROLLERS, DEFAULT_LAW
from tsr_koopman_ctrl.deployment import Deployment, DeploymentError, summary_table
from tsr_koopman_ctrl.evaluation.plots import plot_deployments


def parser():
    p = argparse.ArgumentParser(prog='main_job', description=__doc__.split('\n\n')[0])
    p.add_argument('--law', nargs='+', default=[DEFAULT_LAW, 'koopman_lqr'],
                   choices=sorted(CONTROLLERS),
                   help=f'the laws, each deployed with its defaults (default {DEFAULT_LAW} '
                   'and the paper\'s koopman_lqr)')
    p.add_argument('--steps', type=arguments.STEPS, default=2000)
    p.add_argument('--out', default='lab/results/main_job')
    p.add_argument('--namespace', help="the nodes' ROS namespace (default: the root; every "
                   'deployment has a DDS domain of its own)')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    rows, curves = [], {}
    os.makedirs(args.out, exist_ok=True)
    try:
        for law in args.law:
            run = Deployment(law, steps=args.steps, bags=os.path.join(args.out, 'bags'),
                             logs=os.path.join(args.out, 'logs', law), progress=False,
                             namespace=args.namespace).run()
            rows.append(run.figures)
            curves[law] = (run.loop.tau, run.loop.x, run.loop.u[:-1])
            print(f'{law}: settle tau {run.figures["settle_tau"]}, ratio '
                  f'{run.figures["frontier_ratio"]}', flush=True)
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
    print(table)
    return 0


if __name__ == '__main__':
    sys.exit(main())
