"""The main job: deploy the TSR in closed loop over DDS and leave a bag, plots and a summary.

Starts the simulator (lockstep), the controller and the recorder as three processes on one DDS
domain, waits for the simulator to finish, closes the recorder cleanly, then reads the loop back
from the bag (the record is the source of the figures, not the processes' memory).

    python -m tsr_koopman_ctrl.deploy [--controller koopman_mpc] [--model DIR] [--steps 2000]
                                      [--x0 ...] [--compare]

The default is koopman_mpc on the shipped model (models/koopman_default), which deploys into the
1% zone from the paper's x0 and the comparison's other starts (README).
"""

import argparse
import datetime
import json
import os
import random
import re
import sys
import time

from tsr_sim import dynamics
from tsr_sim.units import Scale

from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl.controllers import CONTROLLERS, DEFAULT_MODEL
from tsr_koopman_ctrl.launcher import NodeProcess
from tsr_koopman_ctrl.metrics import deployment_summary, frontier_tau, OTHER_INITIAL_STATES
from tsr_koopman_ctrl.plots import plot_deployments

COMPUTE_LINE = re.compile(r'compute median ([0-9.]+) us, p99 ([0-9.]+) us')


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--controller', default='koopman_mpc', choices=sorted(CONTROLLERS))
    parser.add_argument('--model', default=DEFAULT_MODEL,
                        help='model directory for the koopman_* controllers')
    parser.add_argument('--steps', type=int, default=2000,
                        help='simulation steps of h = 0.01 tau (paper: 2000)')
    parser.add_argument('--x0', type=float, nargs=4, default=dynamics.PAPER_INITIAL_STATE,
                        metavar=('THETA', 'THETA_RATE', 'L_MINUS_1', 'L_RATE'),
                        help='dimensionless initial state (paper: 0 0 -0.99 0.5)')
    parser.add_argument('--compare', action='store_true',
                        help='every controller from the paper\'s x0 and three others, one '
                        'table and plot (ignores --controller and --x0)')
    parser.add_argument('--out', default='out', help='directory for plots, summary and logs')
    parser.add_argument('--bags', default='bags', help='directory the bag is written in')
    parser.add_argument('--domain', type=int, default=None,
                        help='ROS_DOMAIN_ID (default: a random one in 120..219)')
    parser.add_argument('--timeout', type=float, default=900.0,
                        help='wall seconds before the run is abandoned')
    return parser.parse_args(argv)


def stamp():
    return datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%d_%H%M%S')


def run(args, controller, x0, run_dir, name):
    """One deployment over DDS; returns the bag path. Node logs go to run_dir."""
    if os.path.abspath(args.out) == os.path.abspath(args.bags):
        raise ValueError('--out and --bags must differ: a bag directory holds only the bag')
    os.makedirs(run_dir, exist_ok=True)
    domain = args.domain if args.domain is not None else random.randint(120, 219)
    print(f'[deploy] {controller} from x0 = {[float(v) for v in x0]} for {args.steps} steps '
          f'(tau {args.steps * dynamics.PAPER_STEP:g}) on ROS_DOMAIN_ID {domain}', flush=True)

    def start(package, exe, node, params, console=False):
        log = None if console else os.path.join(run_dir, f'{node}.log')
        return NodeProcess(package, exe, node, params, domain_id=domain, log_path=log)

    recorder = start('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                     {'output_dir': args.bags, 'bag_name': name})
    control = start('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
                    {'controller': controller, 'model': os.path.abspath(args.model),
                     'wait_for_subscribers': 2})
    sim = start('tsr_sim', 'sim_node', 'tsr_sim',
                {'mode': 'lockstep', 'initial_state': [float(v) for v in x0],
                 'max_steps': args.steps, 'exit_on_finish': True, 'wait_for_subscribers': 2,
                 'progress_every': 100}, console=True)
    try:
        watch(sim, (control, recorder), args.timeout, run_dir)
    except KeyboardInterrupt:
        print('[deploy] interrupted: closing the bag', flush=True)
    finally:
        for proc in (sim, control, recorder):
            proc.stop()
    return os.path.join(args.bags, name)


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


def summarise(run_dir, bag_path, controller, x0, planned_steps):
    """Figures of a run read back from its bag (the record, not the processes' memory)."""
    loop = read_loop(bag_path, Scale())
    print(f'[deploy] bag {bag_path}: {loop["report"].summary()}', flush=True)
    summary = deployment_summary(loop['tau'], loop['x'], loop['u'][:-1])
    swing = max(abs(summary['theta_min']), abs(summary['theta_max']))
    paper_start = [float(v) for v in x0] == dynamics.PAPER_INITIAL_STATE.tolist()
    frontier = frontier_tau(swing) if paper_start and summary['settle_tau'] else None
    summary.update(controller=controller, x0=[float(v) for v in x0], bag=bag_path,
                   steps=int(loop['step'][-1]), planned_steps=planned_steps, frontier_tau=frontier,
                   frontier_ratio=frontier and summary['settle_tau'] / frontier,
                   **compute_times(os.path.join(run_dir, 'tsr_controller.log')))
    return summary, (loop['tau'], loop['x'], loop['u'][:-1])


def compute_times(log_path):
    try:
        with open(log_path) as log:
            found = COMPUTE_LINE.findall(log.read())
    except OSError:
        found = []
    if not found:
        return {'compute_median_us': None, 'compute_p99_us': None}
    median, p99 = found[-1]
    return {'compute_median_us': float(median), 'compute_p99_us': float(p99)}


def write_report(run_dir, summaries):
    with open(os.path.join(run_dir, 'summary.json'), 'w') as f:
        json.dump(summaries, f, indent=2)
    table = summary_table(summaries)
    with open(os.path.join(run_dir, 'summary.md'), 'w') as f:
        f.write(table + '\n')
    print(table)
    print(f'[deploy] plots and summary in {run_dir}/', flush=True)


def summary_table(summaries):
    def fmt(v, digits=2):
        return '-' if v is None else f'{v:.{digits}f}'

    def settle(s):
        if s['settle_tau'] is not None:
            return f"{s['settle_tau']:.2f}"
        tau = s['steps'] * dynamics.PAPER_STEP
        return f'left the domain at tau {tau:.2f}' if s['steps'] < s['planned_steps'] \
            else 'not reached'
    rows = ['| controller | x0 | settle tau (1% zone) | final l | theta range [rad] | '
            'l overshoot | max u | integral u dtau | compute median / p99 [us] | '
            'frontier tau | ratio |', '|---|---|---|---|---|---|---|---|---|---|---|']
    for s in summaries:
        final_l = s['final_state'][dynamics.LENGTH_OFFSET] + 1.0
        rows.append(f"| {s['controller']} | {s['x0']} | {settle(s)} | {final_l:.3f} | "
                    f"[{s['theta_min']:.3f}, {s['theta_max']:.3f}] | "
                    f"{s['length_overshoot']:.4f} | {s['tension_max']:.3f} | "
                    f"{s['tension_integral']:.2f} | {fmt(s['compute_median_us'], 0)} / "
                    f"{fmt(s['compute_p99_us'], 0)} | {fmt(s['frontier_tau'], 1)} | "
                    f"{fmt(s['frontier_ratio'])} |")
    return '\n'.join(rows)


def deploy_one(args):
    name = f'deploy_{args.controller}_{stamp()}'
    run_dir = os.path.join(args.out, name)
    bag_path = run(args, args.controller, args.x0, run_dir, name)
    summary, loop = summarise(run_dir, bag_path, args.controller, args.x0, args.steps)
    plot_deployments({args.controller: loop}, os.path.join(run_dir, 'deployment.png'),
                     title=f'TSR deployment over DDS: {args.controller}')
    write_report(run_dir, [summary])
    return [summary]


def compare(args):
    """Every controller from every start, each a full three-process deployment over DDS."""
    compare_dir = os.path.join(args.out, f'compare_{stamp()}')
    summaries = []
    initial_states = (dynamics.PAPER_INITIAL_STATE, *OTHER_INITIAL_STATES)
    starts = [[float(v) for v in x0] for x0 in initial_states]
    for index, x0 in enumerate(starts):
        runs = {}
        for controller in sorted(CONTROLLERS):
            name = f'compare_{controller}_x{index}_{stamp()}'
            run_dir = os.path.join(compare_dir, name)
            bag_path = run(args, controller, x0, run_dir, name)
            summary, runs[controller] = summarise(run_dir, bag_path, controller, x0,
                                                  args.steps)
            summaries.append(summary)
        plot_deployments(runs, os.path.join(compare_dir, f'x0_{index}.png'),
                         title=f'TSR deployment over DDS from x0 = {x0}')
    write_report(compare_dir, summaries)
    return summaries


def main(argv=None):
    args = parse_args(argv)
    try:
        summaries = compare(args) if args.compare else deploy_one(args)
    except (ValueError, RuntimeError, TimeoutError) as err:
        print(f'[deploy] failed: {err}', file=sys.stderr)
        return 1
    if not args.compare and summaries[0]['steps'] < args.steps:
        print(f'[deploy] the simulator stopped at step {summaries[0]["steps"]} of {args.steps}: '
              'the state left the model domain', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
