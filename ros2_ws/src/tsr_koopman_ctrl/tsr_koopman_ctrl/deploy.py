"""The main job: deploy the TSR in closed loop over DDS and leave a bag, plots and a summary.

Starts the simulator (lockstep), the controller and the recorder as three processes on one DDS
domain, waits for the simulator to finish, closes the recorder cleanly, then reads the loop back
from the bag (the record is the source of the figures, not the processes' memory).

    python -m tsr_koopman_ctrl.deploy [--controller linear_lqr] [--steps 2000] [--x0 ...]
"""

import argparse
import datetime
import json
import os
import random
import sys
import time

from tsr_sim import dynamics
from tsr_sim.units import Scale

from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl.controllers import CONTROLLERS
from tsr_koopman_ctrl.launcher import NodeProcess
from tsr_koopman_ctrl.metrics import deployment_summary
from tsr_koopman_ctrl.plots import plot_deployments


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--controller', default='linear_lqr', choices=sorted(CONTROLLERS))
    parser.add_argument('--steps', type=int, default=2000,
                        help='simulation steps of h = 0.01 tau (paper: 2000)')
    parser.add_argument('--x0', type=float, nargs=4, default=dynamics.PAPER_INITIAL_STATE,
                        metavar=('THETA', 'THETA_RATE', 'L_MINUS_1', 'L_RATE'),
                        help='dimensionless initial state (paper: 0 0 -0.99 0.5)')
    parser.add_argument('--out', default='out', help='directory for plots, summary and logs')
    parser.add_argument('--bags', default='bags', help='directory the bag is written in')
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS_DOMAIN_ID (default: a random one in 120..219)')
    parser.add_argument('--timeout', type=float, default=900.0,
                        help='wall seconds before the run is abandoned')
    return parser.parse_args(argv)


def run(args):
    name = f'deploy_{args.controller}_' + \
        datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%d_%H%M%S')
    run_dir = os.path.join(args.out, name)
    if os.path.abspath(args.out) == os.path.abspath(args.bags):
        raise ValueError('--out and --bags must differ: a bag directory holds only the bag')
    os.makedirs(run_dir, exist_ok=True)
    domain = args.domain if args.domain is not None else random.randint(120, 219)
    scale = Scale()
    print(f'[deploy] {args.controller} from x0 = {list(args.x0)} for {args.steps} steps '
          f'(tau {args.steps * dynamics.PAPER_STEP:g}) on ROS_DOMAIN_ID {domain}', flush=True)

    def start(package, exe, node, params, console=False):
        log = None if console else os.path.join(run_dir, f'{node}.log')
        return NodeProcess(package, exe, node, params, domain_id=domain, log_path=log)

    recorder = start('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                     {'output_dir': args.bags, 'bag_name': name})
    controller = start('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
                       {'controller': args.controller, 'wait_for_subscribers': 2})
    sim = start('tsr_sim', 'sim_node', 'tsr_sim',
                {'mode': 'lockstep', 'initial_state': [float(v) for v in args.x0],
                 'max_steps': args.steps, 'exit_on_finish': True, 'wait_for_subscribers': 2,
                 'progress_every': 100}, console=True)
    try:
        watch(sim, (controller, recorder), args.timeout, run_dir)
    except KeyboardInterrupt:
        print('[deploy] interrupted: closing the bag', flush=True)
    finally:
        for proc in (sim, controller, recorder):
            proc.stop()
    return run_dir, os.path.join(args.bags, name), scale


def watch(sim, others, timeout, run_dir):
    """Wait for the simulator to finish; fail early if another node dies or time runs out."""
    deadline = time.monotonic() + timeout
    while sim.running():
        dead = [p.name for p in others if not p.running()]
        if dead:
            raise RuntimeError(f'{", ".join(dead)} exited early: see the logs in {run_dir}')
        if time.monotonic() > deadline:
            raise TimeoutError(f'the deployment did not finish within {timeout} s')
        time.sleep(0.1)


def report(run_dir, bag_path, scale, controller):
    loop = read_loop(bag_path, scale)
    print(f'[deploy] bag {bag_path}: {loop["report"].summary()}', flush=True)
    summary = deployment_summary(loop['tau'], loop['x'], loop['u'][:-1])
    summary.update(controller=controller, bag=bag_path, steps=int(loop['step'][-1]))
    plot_path = os.path.join(run_dir, 'deployment.png')
    plot_deployments({controller: (loop['tau'], loop['x'], loop['u'][:-1])}, plot_path,
                     title=f'TSR deployment over DDS: {controller}')
    with open(os.path.join(run_dir, 'summary.json'), 'w') as f:
        json.dump(summary, f, indent=2)
    table = summary_table([summary])
    with open(os.path.join(run_dir, 'summary.md'), 'w') as f:
        f.write(table + '\n')
    print(table)
    print(f'[deploy] plot {plot_path}; summary {run_dir}/summary.md', flush=True)
    return summary


def summary_table(summaries):
    def fmt(v):
        return 'not reached' if v is None else f'{v:.2f}'
    rows = ['| controller | settle tau (1% zone) | theta range [rad] | l overshoot | '
            'max u | integral u dtau |', '|---|---|---|---|---|---|']
    for s in summaries:
        rows.append(f"| {s['controller']} | {fmt(s['settle_tau'])} | "
                    f"[{s['theta_min']:.3f}, {s['theta_max']:.3f}] | "
                    f"{s['length_overshoot']:.4f} | {s['tension_max']:.3f} | "
                    f"{s['tension_integral']:.2f} |")
    return '\n'.join(rows)


def main(argv=None):
    args = parse_args(argv)
    try:
        run_dir, bag_path, scale = run(args)
    except (ValueError, RuntimeError, TimeoutError) as err:
        print(f'[deploy] failed: {err}', file=sys.stderr)
        return 1
    summary = report(run_dir, bag_path, scale, args.controller)
    if summary['steps'] < args.steps:
        print(f'[deploy] the simulator stopped at step {summary["steps"]} of {args.steps}',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
