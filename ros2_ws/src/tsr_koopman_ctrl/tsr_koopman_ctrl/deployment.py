"""A deployment over DDS from Python: the simulator, the controller and the recorder as three
processes, one run, its result read back from the bag.

    from tsr_koopman_ctrl.deployment import Deployment
    run = Deployment('koopman_mpc', steps=2000).run()
    run.figures['settle_tau'], run.figures['frontier_ratio'], run.loop.x, run.bag

Every figure of a run comes from its bag (`bag.read_loop`, `evaluation.run_figures`), never
from the processes' memory or logs. The nodes start from their installed executables (as
`ros2 run` finds them), on a DDS domain of their own, all on the simulator's clock: the bag
holds one time base, and every step from 0 (the simulator starts once the controller and the
recorder read what it publishes, matched at the DDS level). `deploy` is the command on top;
`tsr_koopman_ctrl.testing` starts a loop for integration tests with the same class.
"""

import dataclasses
import os
import tempfile
import time

import numpy as np
from tsr_sim import dynamics
from tsr_sim.plant import plant_parameters
from tsr_sim.wire import CLOCK_TOPIC

from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl.bag.checks import mark_failed
from tsr_koopman_ctrl.bag.writer import new_bag_name
from tsr_koopman_ctrl.control.registry import (CONTROLLERS, DEFAULT_LAW, law_class,
                                               NODE_SECTIONS, preset, settings_class)
from tsr_koopman_ctrl.control.settings import build
from tsr_koopman_ctrl.evaluation import PAPER_START, run_figures
from tsr_koopman_ctrl.launcher import NodeProcess, reserve_domain
from tsr_koopman_ctrl.model import LiftedModel


class DeploymentError(RuntimeError):
    """A node failed, or the run did not finish in time; the message says which, with the
    last lines of its log."""


class Interrupted(Exception):
    """A deployment stopped by Ctrl-C: its nodes are stopped and its bag is closed, holding the
    steps run so far (`result`, read from it). Callers keep what finished and stop (a loop or
    a comparison must not go on with a cut-short run)."""

    def __init__(self, result):
        super().__init__(f'interrupted: {result.bag} holds the steps run so far')
        self.result = result


@dataclasses.dataclass
class RunResult:
    """One deployment as its bag tells it."""

    bag: str
    loop: object           # bag.RecordedLoop
    figures: dict          # run_figures, the compute times, fallbacks and clamps, the run's setup

    @property
    def halted(self):
        return bool(self.figures['halted'])


def merged_settings(law, settings=None, model=None, preset_name=None):
    """{section: {setting: value}} a deployment gives the controller: the preset's (a name or a
    parameter file), then `settings` on top, then `model` for every law that has a model;
    checked here, so a typo fails before any process starts (ValueError, one line)."""
    merged = {}
    for section, values in (preset(preset_name, NODE_SECTIONS) if preset_name else {}).items():
        merged[section] = dict(values)
    for section, values in (settings or {}).items():
        settings_class(section)        # an unknown section is one line
        if section in CONTROLLERS and section != law:     # the node would never read it
            raise ValueError(f"{section}.{', '.join(values)}: {section} is not the law "
                             f"deployed ({law}); the sections that apply are {law}, "
                             f"{', '.join(NODE_SECTIONS)}")
        merged.setdefault(section, {}).update(values)
    if model is not None:
        path = os.path.abspath(model) if os.path.isdir(model) else model
        with_model = [name for name, cls in CONTROLLERS.items()
                      if 'model' in cls.Settings.__dataclass_fields__]
        if law not in with_model:
            raise ValueError(f'--model: {law} uses no model')
        for name in with_model:
            merged.setdefault(name, {})['model'] = path
    for section, values in merged.items():
        build(settings_class(section), None, values)    # names, types, ranges and choices
    return merged


class Deployment:
    """One closed-loop deployment over DDS (module docstring).

    law: a registry name (`control.CONTROLLERS`); settings: {section: {setting: value}} for the
    law, 'observer' or 'excitation'; model: a model directory or shipped name for the laws that
    have one; preset: a settings preset ('tuned_settle', or a parameter file); plant: a plant
    variant's name, a plant file, or a mapping of plant parameters; x0: the dimensionless start;
    steps: simulator steps of h = 0.01 tau; mode: 'lockstep' (one step per command: the
    deployment as fast as the law computes, deterministic) or 'timed' (the hardware rehearsal:
    `rate_hz` steps per wall second whatever the controller does, the newest state answered);
    namespace: the nodes' ROS namespace; domain: the
    ROS_DOMAIN_ID (default: one no other process on the host uses, `launcher.reserve_domain`,
    reserved until stop()); bags: where the bag goes; logs: where the node
    logs go (default: a new temporary directory); name: the bag's name; timeout: wall seconds
    before the run is abandoned; progress: the simulator's progress lines on this console.
    Bad arguments are one ValueError line, raised here, before any process starts.
    """

    def __init__(self, law=DEFAULT_LAW, settings=None, *, model=None, preset=None,
                 plant='nominal', x0=PAPER_START, steps=2000, mode='lockstep',
                 rate_hz=100.0, namespace=None, domain=None, bags='bags', logs=None, name=None,
                 timeout=900.0, progress=True):
        law_class(law)
        self.law = law
        self.settings = merged_settings(law, settings, model, preset)
        defaults = law_class(law).Settings()
        if hasattr(defaults, 'model'):     # a bad model: one line now, not a failed node later
            LiftedModel.load(self.settings.get(law, {}).get('model', defaults.model))
        self.plant_name = plant if isinstance(plant, str) else 'custom'
        self.plant = dict(plant) if not isinstance(plant, str) else plant_parameters(plant)
        overridden = sorted({'initial_state', 'max_steps'} & set(self.plant))
        if overridden:
            raise ValueError(f'plant {self.plant_name}: {", ".join(overridden)} would be '
                             'overridden by the deployment (give x0 and steps instead)')
        self.x0 = checked_start(x0, self.plant.get('max_swing', dynamics.TUMBLING_SWING))
        if int(steps) < 1:
            raise ValueError(f'steps must be >= 1, got {steps}')
        self.steps = int(steps)
        if mode not in ('lockstep', 'timed'):
            raise ValueError(f"mode must be 'lockstep' or 'timed', got {mode!r}")
        if not float(rate_hz) > 0.0:
            raise ValueError(f'rate_hz must be > 0, got {rate_hz}')
        self.mode, self.rate_hz = mode, float(rate_hz)
        self.namespace = checked_namespace(namespace)
        # Distinct for deployments started in the same second; never an existing directory.
        self.name = name or new_bag_name(bags, f'deploy_{law}')
        self.bags = bags
        self.bag = os.path.join(bags, self.name)
        if os.path.exists(self.bag):
            raise ValueError(f'bag {self.bag} exists: give another name')
        self.logs = logs or tempfile.mkdtemp(prefix=f'{self.name}-logs-')
        self.timeout = float(timeout)
        self.progress = progress
        self.processes = []
        # Last: reserved only once every argument is good, released by stop().
        self.reservation = reserve_domain() if domain is None else None
        self.domain = domain if domain is not None else self.reservation.id

    def node_parameters(self):
        """{node: parameters} of the three processes (`--params-file` of each)."""
        # One time base: every node on the simulator's clock, so the bag's log times and every
        # header stamp are sim time. Nothing is lost at the start: the simulator publishes its
        # first state once the controller and the recorder read it (DDS-matched), the
        # controller commands once the simulator and the recorder read its commands and
        # statuses, and the recorder subscribes at the first /clock, before any state.
        law_settings = {section: values for section, values in self.settings.items()
                        if section in (self.law, *NODE_SECTIONS)}
        lockstep = self.mode == 'lockstep'
        return {
            'tsr_recorder': {'output_dir': self.bags, 'bag_name': self.name,
                             'use_sim_time': True},
            # Lockstep: the controller answers once the simulator and the recorder read its
            # commands and statuses. Timed: at once (the plant does not wait; its writers keep
            # their history for a recorder that matches late).
            'tsr_controller': {'law': self.law, 'use_sim_time': True,
                               'wait_for_subscribers': 2 if lockstep else 0,
                               'wait_for_status_subscribers': 1 if lockstep else 0,
                               **law_settings},
            'tsr_sim': {**self.plant, 'mode': self.mode, 'rate_hz': self.rate_hz,
                        'initial_state': self.x0, 'max_steps': self.steps,
                        'exit_on_finish': True, 'wait_for_subscribers': 2,
                        'progress_every': 100, 'use_sim_time': True}}

    def start(self):
        """Start the recorder, the controller and the simulator (in that order)."""
        os.makedirs(self.logs, exist_ok=True)
        params = self.node_parameters()
        for package, exe, node in (('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder'),
                                   ('tsr_koopman_ctrl', 'controller_node', 'tsr_controller'),
                                   ('tsr_sim', 'sim_node', 'tsr_sim')):
            console = node == 'tsr_sim' and self.progress
            self.processes.append(NodeProcess(
                package, exe, node, params[node], domain_id=self.domain,
                log_path=None if console else os.path.join(self.logs, f'{node}.log'),
                namespace=self.namespace, extra_args=self.clock_remap()))
        return self

    def clock_remap(self):
        """A namespaced loop keeps its clock in its namespace (`/clock` remapped to
        `<namespace>/clock` for each of its nodes): /clock is one topic per domain, and two
        loops on one domain would otherwise run on, and record, each other's clock."""
        if self.namespace in (None, '/'):
            return ()
        return ('-r', f'{CLOCK_TOPIC}:={self.namespace}{CLOCK_TOPIC}')

    def wait(self):
        """Until the simulator finishes; DeploymentError, with the log's tail, if another node
        dies first or time runs out."""
        recorder, control, sim = self.processes
        watch(sim, (control, recorder), self.timeout)

    def stop(self):
        """Stop every node (the simulator first, the recorder last: its bag closes)."""
        for process in reversed(self.processes):
            process.stop()
        if self.reservation is not None:
            self.reservation.release()

    def run(self):
        """Start, wait for the end of the run, stop; the RunResult read from the bag. On Ctrl-C
        the nodes are stopped and the bag closed first, then Interrupted is raised. A run that
        fails (DeploymentError) keeps its bag, marked failed (`bag.checks.mark_failed`): a
        directory of bags given to `retrain` skips it."""
        length = self.x0[dynamics.LENGTH_OFFSET] + 1.0
        print(f'[deploy] {self.law} from x0 = {self.x0} (l = {length:g}) for {self.steps} '
              f'steps (tau {self.steps * dynamics.PAPER_STEP:g}), plant {self.plant_name}, '
              f'on ROS_DOMAIN_ID {self.domain}', flush=True)
        try:
            self.start()
            self.wait()
        except KeyboardInterrupt:
            print('[deploy] interrupted: closing the bag', flush=True)
            self.stop()
            raise Interrupted(self.result())
        except DeploymentError as failure:
            self.stop()                    # the recorder closes the bag first
            if os.path.isdir(self.bag):
                mark_failed(self.bag, str(failure))
            raise
        finally:
            self.stop()
        return self.result()

    def result(self):
        """The run as its bag holds it (the bag must be closed)."""
        return read_result(self.bag, self.law, self.x0, self.steps, self.namespace)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def watch(sim, others, timeout):
    """Wait for the simulator's process to end; DeploymentError, with the log's tail, if one of
    the `others` dies first, time runs out, or the simulator fails."""
    deadline = time.monotonic() + timeout
    while sim.running():
        dead = [p for p in others if not p.running()]
        if dead:
            tails = '\n'.join(f'--- {p.name} exited with {p.process.returncode}; last lines '
                              f'of {p.log_path}:\n{p.log_tail().rstrip()}' for p in dead)
            raise DeploymentError(f'{", ".join(p.name for p in dead)} exited early\n{tails}')
        if time.monotonic() > deadline:
            raise DeploymentError(f'the deployment did not finish within {timeout} s')
        time.sleep(0.1)
    if sim.process.returncode != 0:
        raise DeploymentError(f'{sim.name} exited with {sim.process.returncode}')


def read_result(bag, law, x0, planned_steps, namespace=None):
    """A RunResult from a bag: the figures of the run (`run_figures`), the controller's compute
    times and counters, all read back from the bag."""
    loop = read_loop(bag, namespace=namespace)
    x0 = [float(v) for v in x0]
    figures = run_figures(loop.tau, loop.x, loop.u[:-1], start=x0, halted=loop.halted)
    compute_us = loop.compute_time * 1e6
    status = loop.controller_status
    figures.update(
        controller=law, x0=x0, bag=bag, steps=int(loop.step[-1]), planned_steps=planned_steps,
        halt_tau=loop.halt_tau, halt_reason=loop.halt_reason,
        compute_median_us=float(np.median(compute_us)) if compute_us.size else None,
        compute_p99_us=float(np.percentile(compute_us, 99)) if compute_us.size else None,
        solver_fallbacks=status.solver_fallbacks if status else None,
        clamped=status.clamped if status else None,
        supervisor_switches=status.supervisor_switches if status else None,
        fallback_steps=loop.fallback_steps,
        safety_corrections=loop.corrections,
        dropped_states=status.dropped_states if status else None,
        overruns=status.overruns if status else None)
    return RunResult(bag=bag, loop=loop, figures=figures)


def checked_start(x0, max_swing=dynamics.TUMBLING_SWING):
    """The start as 4 floats [theta, theta', l - 1, l'] (ValueError, one line, for one the
    simulator would refuse or halt at once: outside the domain, 0 < l <= PLAUSIBLE_LENGTH, or
    swinging past `max_swing`)."""
    start = [float(v) for v in x0]
    if len(start) != dynamics.PLANAR_DIM or not np.all(np.isfinite(start)):
        raise ValueError(f'x0 {start} is not 4 finite values [theta, theta\', l - 1, l\']')
    length = start[dynamics.LENGTH_OFFSET] + 1.0
    if not 0.0 < length <= dynamics.PLAUSIBLE_LENGTH:
        raise ValueError(f'x0 {start} is outside the model domain: l = {length:g}, not in '
                         f'(0, {dynamics.PLAUSIBLE_LENGTH:g}] (the third value is l - 1: the '
                         "paper's start l = 0.01 is -0.99)")
    if abs(start[dynamics.THETA]) > max_swing:
        raise ValueError(f'x0 {start} is outside the model domain: |theta| = '
                         f'{abs(start[dynamics.THETA]):g} rad is past max_swing {max_swing:g} '
                         '(tumbling)')
    return start


def checked_namespace(namespace):
    """An absolute ROS namespace, as `ros2 launch` pushes one (ValueError, one line, if it is
    not a valid one); None stays None."""
    if namespace is None:
        return None
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_namespace import validate_namespace
    namespace = namespace if namespace.startswith('/') else '/' + namespace
    try:
        validate_namespace(namespace)
    except NameValidationException as error:
        # rclpy's message ends its first line with ':' and the name on the next
        reason = ' '.join(line.strip() for line in str(error).splitlines()[:2])
        raise ValueError(f'--namespace {namespace!r}: {reason}') from None
    return namespace


def settle_cell(row):
    if row['settle_tau'] is not None:
        return f"{row['settle_tau']:.2f}"
    if row['halted']:
        reason = row.get('halt_reason') or 'halted'
        return reason if row['halt_tau'] is None else f"{reason} at tau {row['halt_tau']:.2f}"
    if row['steps'] < row['planned_steps']:
        return f"stopped at step {row['steps']}"
    return 'not reached'


def _fixed(value, digits=2):
    return '-' if value is None else f'{value:.{digits}f}'


def _ms(us):
    return '-' if us is None else f'{us / 1000:.3g}'


#: The deployment table's columns: header -> the cell of a run's figures. The README's
#: headline (`lab.main_job`) shows some of them under the same headers, in the same units.
COLUMNS = {
    'law': lambda r: r['controller'],
    'x0': lambda r: str(r['x0']),
    'settle tau (1% zone)': settle_cell,
    'final l': lambda r: f"{r['final_state'][dynamics.LENGTH_OFFSET] + 1.0:.3f}",
    'swing [rad]': lambda r: f"{r['swing']:.3f}",
    'l overshoot': lambda r: f"{100 * r['length_overshoot']:.2f}%",
    'max u': lambda r: f"{r['tension_max']:.2f}",
    'integral u dtau': lambda r: f"{r['tension_integral']:.2f}",
    'compute median / p99 [ms]':
        lambda r: f"{_ms(r['compute_median_us'])} / {_ms(r['compute_p99_us'])}",
    'fallback flew [steps] (switches)':
        lambda r: f"{r.get('fallback_steps', 0)} ({r.get('supervisor_switches') or 0})",
    'safety filter corrected [steps]': lambda r: str(r.get('safety_corrections') or 0),
    'minimum time at that swing [tau]': lambda r: _fixed(r['frontier_tau'], 1),
    'ratio': lambda r: _fixed(r['frontier_ratio']),
}


def summary_table(rows, columns=tuple(COLUMNS)):
    """The deployment table (markdown), one row per run's figures, of `columns` (COLUMNS)."""
    lines = ['| ' + ' | '.join(columns) + ' |', '|' + '---|' * len(columns)]
    lines += ['| ' + ' | '.join(COLUMNS[column](r) for column in columns) + ' |'
              for r in rows]
    return '\n'.join(lines)
