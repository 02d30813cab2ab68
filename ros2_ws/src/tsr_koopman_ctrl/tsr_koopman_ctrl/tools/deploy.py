"""The main job: deploy the TSR in closed loop over DDS and leave a bag, plots and a summary.

Starts the simulator (lockstep), the controller and the recorder as three processes on one DDS
domain, waits for the simulator to finish, closes the recorder cleanly, then reads the loop back
from the bag: every figure of the table (settle time, swing, tensions, the controller's compute
times, a halt) comes from the record, not from the processes' memory or logs.

    python -m tsr_koopman_ctrl.tools.deploy [--law koopman_mpc] [--model DIR|NAME]
        [--set LAW.SETTING=VALUE ...] [--steps 2000] [--x0 ...] [--namespace NS] [--compare]

The default is koopman_mpc on the shipped model (koopman_default), which deploys into the 1% zone
from every comparison start (README).
"""

import argparse
import datetime
import os
import sys
import time

import numpy as np
from tsr_sim import dynamics
from tsr_sim.plant import plant_parameters

from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl.control.registry import DEFAULT_LAW, law_class, NODE_SECTIONS, preset
from tsr_koopman_ctrl.control.settings import parse_value
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, run_figures
from tsr_koopman_ctrl.evaluation.plots import plot_deployments
from tsr_koopman_ctrl.model import LiftedModel
from tsr_koopman_ctrl.tools import cli
from tsr_koopman_ctrl.tools.launcher import NodeProcess, random_domain_id
from tsr_koopman_ctrl.tools.report import write_report


def parse_args(argv):
    parser = argparse.ArgumentParser(prog='deploy', description=__doc__.split('\n\n')[0])
    parser.add_argument('--law', default=DEFAULT_LAW, choices=sorted(CONTROLLERS),
                        help=f'the control law (default {DEFAULT_LAW})')
    parser.add_argument('--model', help='model directory or shipped model name for the '
                        'koopman_* laws (default: their `model` setting, koopman_default)')
    parser.add_argument('--preset', help="a settings preset for the laws ('untuned': "
                        "config/untuned.yaml, the settings before tuning; 'tuned_ratio': "
                        'config/tuned_ratio.yaml, tuned for the frontier ratio; '
                        "'tuned_cross': config/tuned_cross.yaml, with cross terms in Q; or a "
                        'parameter file); --set applies on top')
    parser.add_argument('--set', action='append', default=[], metavar='LAW.SETTING=VALUE',
                        help='a law setting (repeatable), e.g. koopman_mpc.horizon=8, the '
                        'observer (offset-free control, on by default): '
                        'observer.disturbance=none, or the excitation: excitation.kind=prbs; '
                        'sequences as a,b,c')
    parser.add_argument('--plant', default='nominal',
                        help='plant variant: a name under tsr_sim/config/plants (actuator_weak, '
                        'actuator_strong, heavy_robot, out_of_plane, eccentric_orbit, '
                        'noisy_sensors) or a YAML file of plant parameters (tsr_sim.plant.'
                        'PLANT_FILE_PARAMETERS)')
    parser.add_argument('--steps', type=cli.STEPS, default=2000,
                        help='simulation steps of h = 0.01 tau (paper: 2000)')
    parser.add_argument('--x0', type=float, nargs=4, default=dynamics.PAPER_INITIAL_STATE,
                        metavar=('THETA', 'THETA_RATE', 'L_MINUS_1', 'L_RATE'),
                        help='dimensionless initial state (paper: 0 0 -0.99 0.5)')
    parser.add_argument('--compare', action='store_true',
                        help='every controller from every comparison start, one table and a '
                        'plot per start (ignores --law and --x0)')
    parser.add_argument('--out', default='out', type=cli.output_dir,
                        help='directory for plots, summary and logs')
    parser.add_argument('--bags', default='bags', type=cli.output_dir,
                        help='directory the bag is written in')
    parser.add_argument('--namespace', default=None, help='ROS namespace of the three nodes')
    parser.add_argument('--domain', type=cli.DOMAIN_ID, default=None,
                        help='ROS_DOMAIN_ID (default: a random one in 1..101, not the '
                             'environment\'s ROS_DOMAIN_ID)')
    parser.add_argument('--timeout', type=cli.number(above=0), default=900.0,
                        help='wall seconds before the run is abandoned')
    args = parser.parse_args(argv)
    try:
        args.law_settings = law_settings(args.set, args.model)
        for law, values in (preset(args.preset, NODE_SECTIONS) if args.preset else {}).items():
            args.law_settings[law] = {**values, **args.law_settings.get(law, {})}
    except ValueError as error:
        parser.error(str(error))
    if not dynamics.in_domain(np.asarray(args.x0, dtype=float)):
        parser.error(f'--x0 {list(args.x0)} is outside the model domain (finite, l - 1 > -1)')
    if os.path.abspath(args.out) == os.path.abspath(args.bags):
        parser.error('--out and --bags must differ: a bag directory holds only the bag')
    try:
        args.plant_parameters = plant_parameters(args.plant)
        check_models(args)
    except ValueError as error:
        parser.error(str(error))
    # The run's start and length are deploy's to set: a plant file's would be overridden.
    overridden = sorted({'initial_state', 'max_steps'} & set(args.plant_parameters))
    if overridden:
        parser.error(f'--plant {args.plant}: {", ".join(overridden)} would be overridden by '
                     f'deploy (give --x0 and --steps instead)')
    if args.namespace is not None:
        from rclpy.exceptions import NameValidationException
        from rclpy.validate_namespace import validate_namespace
        if not args.namespace.startswith('/'):
            args.namespace = '/' + args.namespace     # as `ros2 launch` pushes one: absolute
        try:
            validate_namespace(args.namespace)
        except NameValidationException as error:
            # rclpy's message ends its first line with ':' and the name on the next
            reason = ' '.join(line.strip() for line in str(error).splitlines()[:2])
            parser.error(f'--namespace {args.namespace!r}: {reason}')
    return args


def check_models(args):
    """Load the model of every law that will run and has one: a bad one is a usage error
    here, not a controller that fails to start after the other nodes have."""
    laws = sorted(CONTROLLERS) if args.compare else [args.law]
    with_model = [law for law in laws if 'model' in law_class(law).Settings.__dataclass_fields__]
    if args.model is not None and not with_model:
        raise ValueError(f'--model: {args.law} uses no model')
    for law in with_model:
        default = law_class(law).Settings().model
        LiftedModel.load(args.law_settings.get(law, {}).get('model', default))


def settings_class(section):
    """The settings class of a --set section: a law's, the observer's or the excitation's."""
    return NODE_SECTIONS.get(section) or law_class(section).Settings


def law_settings(assignments, model):
    """{section: {setting: value}} from --set SECTION.SETTING=VALUE (a law, or `excitation`)
    and --model, checked here so a typo fails before any process starts."""
    settings = {}
    for assignment in assignments:
        key, sep, text = assignment.partition('=')
        section, dot, name = key.partition('.')
        if not (sep and dot):
            raise ValueError(f'--set takes LAW.SETTING=VALUE, got {assignment!r}')
        settings.setdefault(section, {})[name] = parse_value(settings_class(section), name,
                                                             text)
    if model is not None:
        for law, cls in CONTROLLERS.items():
            if 'model' in {f for f in cls.Settings.__dataclass_fields__}:
                path = os.path.abspath(model) if os.path.isdir(model) else model
                settings.setdefault(law, {})['model'] = path
    for section, values in settings.items():
        settings_class(section)(**values)   # ranges and choices, one line if wrong
    return settings


def stamp():
    return datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%d_%H%M%S')


class Interrupted(Exception):
    """A deployment stopped by Ctrl-C: its nodes are stopped and its bag is closed, holding the
    steps run so far. Callers keep what finished and stop (a loop or a comparison must not go
    on with a cut-short run)."""

    def __init__(self, bag_path):
        super().__init__(f'interrupted: {bag_path} holds the steps run so far')
        self.bag_path = bag_path


def run(args, controller, x0, run_dir, name):
    """One deployment over DDS; returns the bag path (raises Interrupted on Ctrl-C, once the
    bag is closed). Node logs go to run_dir."""
    os.makedirs(run_dir, exist_ok=True)
    domain = args.domain if args.domain is not None else random_domain_id()
    print(f'[deploy] {controller} from x0 = {[float(v) for v in x0]} for {args.steps} steps '
          f'(tau {args.steps * dynamics.PAPER_STEP:g}), plant {args.plant}, on ROS_DOMAIN_ID '
          f'{domain}', flush=True)

    def start(package, exe, node, params, console=False):
        log = None if console else os.path.join(run_dir, f'{node}.log')
        return NodeProcess(package, exe, node, params, domain_id=domain, log_path=log,
                           namespace=args.namespace)

    # One time base: every node on the simulator's clock, so the bag's log times and every
    # header stamp are sim time. Nothing is lost at the start: the simulator publishes its
    # first state once the controller and the recorder read it (DDS-matched), the controller
    # commands once the simulator and the recorder read its commands and statuses, and the
    # recorder subscribes at the first /clock, before any state.
    recorder = start('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                     {'output_dir': args.bags, 'bag_name': name, 'use_sim_time': True})
    law = {section: args.law_settings[section] for section in (controller, *NODE_SECTIONS)
           if args.law_settings.get(section)}
    control = start('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
                    {'law': controller, 'wait_for_subscribers': 2,
                     'wait_for_status_subscribers': 1, 'use_sim_time': True, **law})
    sim = start('tsr_sim', 'sim_node', 'tsr_sim',
                {**args.plant_parameters, 'mode': 'lockstep',
                 'initial_state': [float(v) for v in x0],
                 'max_steps': args.steps, 'exit_on_finish': True, 'wait_for_subscribers': 2,
                 'progress_every': 100, 'use_sim_time': True}, console=True)
    interrupted = False
    try:
        watch(sim, (control, recorder), args.timeout)
    except KeyboardInterrupt:
        print('[deploy] interrupted: closing the bag', flush=True)
        interrupted = True
    finally:
        for proc in (sim, control, recorder):
            proc.stop()
    if interrupted:
        raise Interrupted(os.path.join(args.bags, name))
    return os.path.join(args.bags, name)


def watch(sim, others, timeout):
    """Wait for the simulator to finish; fail early, with the log's tail, if another node dies
    or time runs out."""
    deadline = time.monotonic() + timeout
    while sim.running():
        dead = [p for p in others if not p.running()]
        if dead:
            tails = '\n'.join(f'--- {p.name} exited with {p.process.returncode}; last lines of '
                              f'{p.log_path}:\n{p.log_tail().rstrip()}' for p in dead)
            raise RuntimeError(f'{", ".join(p.name for p in dead)} exited early\n{tails}')
        if time.monotonic() > deadline:
            raise TimeoutError(f'the deployment did not finish within {timeout} s')
        time.sleep(0.1)
    if sim.process.returncode != 0:
        raise RuntimeError(f'{sim.name} exited with {sim.process.returncode} (its log is above)')


def summarise(bag_path, controller, x0, planned_steps, namespace=None):
    """Figures of a run, read back from its bag alone."""
    loop = read_loop(bag_path, namespace=namespace)
    print(f'[deploy] bag {bag_path}: {loop.report.summary()}', flush=True)
    x0 = [float(v) for v in x0]
    row = run_figures(loop.tau, loop.x, loop.u[:-1], start=x0, halted=loop.halted)
    compute_us = loop.compute_time * 1e6
    status = loop.controller_status
    row.update(controller=controller, x0=x0, bag=bag_path, steps=int(loop.step[-1]),
               planned_steps=planned_steps, halt_tau=loop.halt_tau,
               compute_median_us=float(np.median(compute_us)) if compute_us.size else None,
               compute_p99_us=float(np.percentile(compute_us, 99)) if compute_us.size else None,
               solver_fallbacks=status.solver_fallbacks if status else None,
               clamped=status.clamped if status else None)
    return row, (loop.tau, loop.x, loop.u[:-1])


def deploy_one(args):
    """The deployment, summarised; an interrupted one is summarised as far as it ran, then
    Interrupted is raised again."""
    name = f'deploy_{args.law}_{stamp()}'
    run_dir = os.path.join(args.out, name)
    try:
        bag_path, stopped = run(args, args.law, args.x0, run_dir, name), None
    except Interrupted as interruption:
        bag_path, stopped = interruption.bag_path, interruption
    row, loop = summarise(bag_path, args.law, args.x0, args.steps, args.namespace)
    plot_deployments({args.law: loop}, os.path.join(run_dir, 'deployment.png'),
                     title=f'TSR deployment over DDS: {args.law}')
    write_report(run_dir, [row])
    if stopped is not None:
        raise stopped
    return [row]


def compare(args):
    """Every controller from every comparison start, each a three-process deployment."""
    compare_dir = os.path.join(args.out, f'compare_{stamp()}')
    rows = []
    try:
        for index, x0 in enumerate(COMPARISON_STARTS):
            runs = {}
            for controller in sorted(CONTROLLERS):
                name = f'compare_{controller}_x{index}_{stamp()}'
                bag_path = run(args, controller, x0, os.path.join(compare_dir, name), name)
                row, runs[controller] = summarise(bag_path, controller, x0, args.steps,
                                                  args.namespace)
                rows.append(row)
            plot_deployments(runs, os.path.join(compare_dir, f'x0_{index}.png'),
                             title=f'TSR deployment over DDS from x0 = {list(x0)}')
    except Interrupted:
        if rows:                       # the table of the runs that finished
            write_report(compare_dir, rows)
        raise
    write_report(compare_dir, rows)
    return rows


def main(argv=None):
    args = parse_args(argv)
    try:
        rows = compare(args) if args.compare else deploy_one(args)
    except Interrupted as stopped:
        print(f'[deploy] {stopped}', file=sys.stderr)
        return cli.INTERRUPTED_STATUS
    except (ValueError, RuntimeError, TimeoutError, FileNotFoundError) as err:
        print(f'[deploy] failed: {err}', file=sys.stderr)
        return 1
    if not args.compare and rows[0]['halted']:
        print(f'[deploy] the state left the model domain at tau {rows[0]["halt_tau"]:.2f}',
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
