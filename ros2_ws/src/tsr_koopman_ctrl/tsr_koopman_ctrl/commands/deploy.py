"""The main job: deploy the TSR in closed loop over DDS and leave a bag, a plot and a summary.

    ros2 run tsr_koopman_ctrl deploy [--law koopman_mpc] [--model DIR|NAME] [--preset NAME]
        [--set SECTION.SETTING=VALUE ...] [--plant NAME|FILE] [--steps 2000] [--x0 ...]
        [--mode lockstep|timed] [--namespace NS]

Starts the simulator (lockstep, or `--mode timed`: the hardware rehearsal), the controller and
the recorder as three processes on a DDS domain of their own (`deployment.Deployment`), waits
for the run to end, closes the bag and reads the run back from it: every figure of the table
comes from the bag. Exit status 1 if the simulator halted the run (the robot tumbled, or the
state left the domain) or a node failed (the bag is kept, marked failed: `retrain` skips it
below a directory), 2 for a bad option (one line, before any node starts), 130 on Ctrl-C (the
bag is closed and the steps run so far summarised).
"""

import argparse
import os
import sys

from tsr_sim import dynamics

from tsr_koopman_ctrl.bag.checks import FAILED_MARK, is_failed
from tsr_koopman_ctrl.commands import cli
from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl.control.registry import DEFAULT_LAW, parse_assignments
from tsr_koopman_ctrl.deployment import (Deployment, DeploymentError, Interrupted,
                                         summary_table)
from tsr_koopman_ctrl.evaluation.plots import plot_deployments


def parse_args(argv):
    parser = argparse.ArgumentParser(prog='deploy', description=__doc__.split('\n\n')[0])
    parser.add_argument('--law', default=DEFAULT_LAW, choices=sorted(CONTROLLERS),
                        help=f'the control law (default {DEFAULT_LAW})')
    parser.add_argument('--model', help='model directory or shipped model name for the laws '
                        'that have a model (default: their `model` setting)')
    parser.add_argument('--preset', help="a settings preset ('untuned', 'tuned_settle', "
                        "'tuned_cross' under the installed config/, or a parameter file); "
                        '--set applies on top')
    parser.add_argument('--set', action='append', default=[], metavar='SECTION.SETTING=VALUE',
                        help='a setting of the law deployed (koopman_mpc.horizon=8 with '
                        '--law koopman_mpc; another law\'s is refused), the observer '
                        '(observer.disturbance=none: the bare law), the excitation '
                        '(excitation.kind=prbs), the supervisor (supervisor.fallback=none: '
                        'the learned law unwatched) or the safety filter '
                        '(safety_filter.backup=none); repeatable; sequences as a,b,c')
    parser.add_argument('--plant', default='nominal',
                        help='plant variant: a name under tsr_sim/config/plants (actuator_weak, '
                        'actuator_strong, heavy_robot, out_of_plane, eccentric_orbit, '
                        'noisy_sensors) or a YAML file of plant parameters')
    parser.add_argument('--steps', type=cli.STEPS, default=2000,
                        help='simulation steps of h = 0.01 tau (paper: 2000)')
    parser.add_argument('--mode', default='lockstep', choices=('lockstep', 'timed'),
                        help='lockstep: one simulator step per command (as fast as the law '
                        'computes); timed: --rate-hz steps per wall second whatever the '
                        'controller does, as hardware runs (the newest state answered)')
    parser.add_argument('--rate-hz', type=cli.number(above=0), default=100.0,
                        help='timed mode: simulator steps per wall second (default 100)')
    parser.add_argument('--x0', type=float, nargs=4, default=dynamics.PAPER_INITIAL_STATE,
                        metavar=('THETA', 'THETA_RATE', 'L_MINUS_1', 'L_RATE'),
                        help="dimensionless initial state; the third value is l - 1, not l "
                        "(default: the paper's start l = 0.01, l' = 0.5: 0 0 -0.99 0.5)")
    parser.add_argument('--out', default='out', type=cli.output_dir,
                        help='directory for the plot, the summary and the node logs')
    parser.add_argument('--bags', default='bags', type=cli.output_dir,
                        help='directory the bag is written in')
    parser.add_argument('--namespace', default=None, help='ROS namespace of the three nodes')
    parser.add_argument('--domain', type=cli.DOMAIN_ID, default=None,
                        help="ROS_DOMAIN_ID (default: one of 1..101 that no other process "
                             "on this host uses and not the environment's ROS_DOMAIN_ID, "
                             'reserved for the run)')
    parser.add_argument('--timeout', type=cli.number(above=0), default=900.0,
                        help='wall seconds before the run is abandoned')
    args = parser.parse_args(argv)
    if os.path.abspath(args.out) == os.path.abspath(args.bags):
        parser.error('--out and --bags must differ: a bag directory holds only the bag')
    try:
        settings = parse_assignments(args.set)
        args.deployment = Deployment(
            args.law, settings, model=args.model, preset=args.preset, plant=args.plant,
            x0=args.x0, steps=args.steps, mode=args.mode, rate_hz=args.rate_hz,
            namespace=args.namespace, domain=args.domain,
            bags=args.bags, timeout=args.timeout)
    except ValueError as error:
        parser.error(str(error))
    deployment = args.deployment
    deployment.logs = os.path.join(args.out, deployment.name)
    length = deployment.x0[dynamics.LENGTH_OFFSET] + 1.0
    if length > 1.0:
        print(f'[deploy] note: --x0 starts at l = {length:g}, past the full tether length (the '
              "third value is l - 1: the paper's l = 0.01 is -0.99)", file=sys.stderr)
    return args


def report(result, directory):
    """The plot and the summary table (summary.md, summary.json) of a run, printed too."""
    import json
    os.makedirs(directory, exist_ok=True)
    loop = result.loop
    plot_deployments({result.figures['controller']: (loop.tau, loop.x, loop.u[:-1])},
                     os.path.join(directory, 'deployment.png'),
                     title=f'TSR deployment over DDS: {result.figures["controller"]}')
    table = summary_table([result.figures])
    with open(os.path.join(directory, 'summary.md'), 'w') as f:
        f.write(table + '\n')
    with open(os.path.join(directory, 'summary.json'), 'w') as f:
        json.dump([result.figures], f, indent=2)
    print(f'[deploy] bag {result.bag}: {loop.report.summary()}')
    print(table)
    print(f'[deploy] plot and summary in {directory}/', flush=True)


def main(argv=None):
    args = parse_args(argv)
    deployment = args.deployment
    try:
        result = deployment.run()
    except Interrupted as stopped:
        report(stopped.result, deployment.logs)
        print(f'[deploy] {stopped}', file=sys.stderr)
        return cli.INTERRUPTED_STATUS
    except (ValueError, DeploymentError, FileNotFoundError) as error:
        print(f'[deploy] failed: {error}', file=sys.stderr)
        if is_failed(deployment.bag):
            print(f'[deploy] the bag of the failed run is kept in {deployment.bag}, marked '
                  f'failed ({FAILED_MARK}): retrain skips it below a directory',
                  file=sys.stderr)
        return 1
    report(result, deployment.logs)
    if result.halted:
        print(f'[deploy] {halt_line(result.loop)}', file=sys.stderr)
        return 1
    return 0


def halt_line(loop):
    """Why and when the simulator halted the run, in its own words where the bag has them."""
    said = loop.sim_status.message.split('; integration stopped')[0]
    when = '' if loop.halt_tau is None else f' at tau {loop.halt_tau:.2f}'
    return f'the run halted{when}: {loop.halt_reason}' + (f' ({said})' if said else '')


if __name__ == '__main__':
    sys.exit(main())
