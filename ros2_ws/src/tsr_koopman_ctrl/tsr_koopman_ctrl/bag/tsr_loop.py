"""The deployment loop read back from a bag: the record every figure of a run comes from.

Messages are told apart by type, not by topic name, so a loop recorded under any namespace reads
back; a bag holding more than one loop needs the namespace to pick one. A bag needs only
`tsr/state` and `tsr/tension_cmd` (as hardware, or another tool, writes one); the simulator's
RunInfo and statuses and the controller's statuses are read when they are there.

Order. "Before" and "after" below are the order the messages were recorded in: the bag's files
in split order and the messages of each file in file order, which is the order the recorder
received them (the project's recorder's log times follow it; another recorder on sim time logs
the sim clock, which goes back at a reset).

Runs. The simulator numbers its runs: `TsrState.run` is 0 at start and one more at each reset
(`tsr/reset`). A run is the states carrying one number, in step order; the runs are in the order
of their numbers (`RecordedLoop.run` is the index in the bag, `sim_run` the simulator's number).
A state recorded again with the same values (the lockstep simulator's idle republish, a late
joiner's history) counts once; one recorded again with other values (a second publisher) is a
conflicting state: the first is kept, the step is flagged (`conflicting`) and counted. A bag
whose states carry no run number (recorded under an older TsrState) is refused.

Commands, `match`:
  'step'  A lockstep simulator steps with the command answering its state: a command,
          excitation or controller status (each carries the step it answers) belongs to the
          run whose state of that step was recorded last before it (a late answer to the
          previous run stays there), else to the first run recording that state after it
          (delivery across topics is not ordered), else to the run in progress when it was
          recorded. `u` is the first command answering each step, the one the simulator
          applies; so no command of one run is ever matched to a state of another.
  'time'  A timed simulator or hardware applies the last command it received, whatever step
          it carries (zero-order hold): the tension over the sample from state k to the next
          is that of the last command recorded after the run's first state and before the
          next state of the run (for the last state, before the next run or the bag's end).
          A command received mid-sample counts for the whole sample, as the timed simulator,
          which applies the tension it holds at the tick, does. A command with `hold` set
          (the controller stopped) or a simulator status saying the plant holds leaves no
          tension in force (NaN, `held`) until the next command without `hold`; a run starts
          with none (the plant's own reset tension is not in the bag).
Default (None): 'step' when the simulator's RunInfo says lockstep, else 'time' (a timed
simulator, hardware, a bag without RunInfo). Excitation and controller statuses are matched by
step either way; a simulator status by the run number it carries.

Units and sample period. The units scale is the simulator's (RunInfo), else `scale`, else the
paper's (`tsr_sim.units.Scale()`). The sample period `h` [tau] is the simulator's `step`
(RunInfo), else `sample_period` [s] converted with the scale, else the median over the runs of
the states' header-stamp differences per step (None when the stamps give none).

`read_loop` refuses a bag of several runs unless given `run=k`; `read_runs` returns them all.
"""

import bisect
from dataclasses import dataclass, field
import math
import warnings

import numpy as np
from tsr_sim import wire
from tsr_sim.units import Scale
import yaml

from tsr_koopman_ctrl.bag.reader import BagReader, ReadReport

STATE_TYPE = wire.LOOP_TOPIC_TYPES[wire.STATE_TOPIC]
TENSION_TYPE = wire.LOOP_TOPIC_TYPES[wire.TENSION_TOPIC]
SIM_STATUS_TYPE = wire.LOOP_TOPIC_TYPES[wire.SIM_STATUS_TOPIC]
CONTROLLER_STATUS_TYPE = wire.LOOP_TOPIC_TYPES[wire.CONTROLLER_STATUS_TOPIC]
#: tsr_msgs/SimStatus.status of a plant that stopped because the state left the domain (or
#: tumbled, or the tether paid out too far: its message says which, `halt_reason`).
HALTED_OUT_OF_DOMAIN = 1
#: Why the simulator halted a run, by how its SimStatus.message begins (`tsr_sim.plant.Plant`).
HALT_REASONS = (('tumbling', 'tumbled'), ('the tether paid out', 'paid out too far'),
                ('state left the model domain', 'left the domain'))
#: ControllerStatus.status values that mean a command was computed (and timed).
COMPUTED = (0, 1, 2)
#: How commands are matched to states (module docstring).
BY_STEP, BY_TIME = 'step', 'time'
MATCHES = (BY_STEP, BY_TIME)
#: Where the sample period came from.
H_FROM_RUN_INFO, H_FROM_OPTION, H_FROM_STAMPS = 'run_info', 'option', 'stamps'
H_SOURCES = {H_FROM_RUN_INFO: "the simulator's RunInfo", H_FROM_OPTION: 'the option given',
             H_FROM_STAMPS: "the states' stamps"}
#: A sample period given in seconds matches a model's within this (relative): the period as
#: printed to 5 significant digits (`bag runs`: 8.4717 s) or to 4 (8.472 s) passes.
GIVEN_PERIOD_TOLERANCE = 1e-4
#: Where the units came from.
UNITS_FROM_RUN_INFO, UNITS_GIVEN, UNITS_DEFAULT = 'run_info', 'given', 'default'
UNITS_SOURCES = {UNITS_FROM_RUN_INFO: "the simulator's RunInfo", UNITS_GIVEN: 'as given',
                 UNITS_DEFAULT: "the paper's"}


class BagWarning(UserWarning):
    """A bag read as far as it can be, with something the caller should know (one line)."""


def halt_reason(message):
    """'tumbled', 'paid out too far' or 'left the domain': why the simulator halted a run,
    from its status message ('halted' for a message it does not begin with)."""
    return next((reason for start, reason in HALT_REASONS if message.startswith(start)),
                'halted')


@dataclass
class RecordedLoop:
    """One deployment as recorded. Arrays are per state step, in the paper's variables; `u`
    is the tension over the sample from each state (by step: the first command answering it;
    by time: the one in force; module docstring), NaN where none."""

    step: np.ndarray              # (N,) state steps, ascending, each once
    tau: np.ndarray               # (N,)
    x: np.ndarray                 # (N, n) dimensionless states (republished states count once)
    u: np.ndarray                 # (N,) dimensionless tension over the sample from each state
    namespace: str = '/'
    sim_status: object = None     # the last tsr_msgs/SimStatus of the run, decoded
    controller_status: object = None   # the last tsr_msgs/ControllerStatus, decoded
    compute_time: np.ndarray = field(default_factory=lambda: np.zeros(0))   # [s] per command
    report: ReadReport = None
    scale: Scale = None           # the units the dimensionless arrays were converted with
    #: What the nodes ran with ('simulator', 'controller': their RunInfo, parsed): the plant
    #: variant, the law, its settings and model, the units scale.
    run_info: dict = field(default_factory=dict)
    excitation: np.ndarray = None   # (N,) dimensionless tension the controller added per step
    tension: np.ndarray = None    # (N,) [N] the command of `u` as recorded (SI), NaN where none
    run: int = 0                  # which run of the bag this is: 0, 1, ... in order
    runs: int = 1                 # how many the bag holds
    sim_run: int = 0              # the simulator's number of the run (TsrState.run)
    #: Message counts of the run: states (every message of the run), republished_states,
    #: conflicting_states (a step recorded again with other values), commands (every command
    #: of the run); by step also repeated_commands (identical to the first of their step),
    #: conflicting_commands (differing from it), orphan_commands (steps no state of the run has).
    counts: dict = field(default_factory=dict)
    h: float = None               # sample period [tau] (None: unknown)
    h_source: str = None          # 'run_info', 'option' or 'stamps'
    match: str = BY_STEP          # how commands were matched: 'step' or 'time'
    units: str = UNITS_DEFAULT    # where `scale` came from: 'run_info', 'given' or 'default'
    held: np.ndarray = None       # (N,) by time: the plant held the tether (no tension)
    conflicting: np.ndarray = None   # (N,) the step was recorded again with another state
    #: (N,) under the runtime-assurance supervisor, which law flew each step ('learned',
    #: 'fallback'; '' without a supervisor or where no command was computed) and why the
    #: monitor distrusted the learned law then ('' when it did not): ControllerStatus.
    flying: np.ndarray = None
    monitor: np.ndarray = None
    #: (N,) under the predictive safety filter, how each step was answered ('certified',
    #: 'verified', 'handed_over', 'kept', 'replanned', 'lapsed', 'uncertified'; '' without a
    #: filter or where no command was computed) and the dimensionless tension the filtered
    #: law asked for (NaN: none): ControllerStatus.certificate, requested_tension.
    certificate: np.ndarray = None
    requested: np.ndarray = None

    @property
    def corrections(self):
        """Steps the safety filter flew another tension than the filtered law's: every step
        it did not pass (certified, or the supervisor's fallback flying: verified)."""
        if self.certificate is None:
            return 0
        passed = np.isin(self.certificate, ('', 'certified', 'verified'))
        return int(np.count_nonzero(~passed))

    @property
    def fallback_steps(self):
        """Steps the supervisor's fallback flew."""
        return int(np.count_nonzero(self.flying == 'fallback')) if self.flying is not None \
            else 0

    @property
    def halted(self):
        """True if the simulator halted the run: the state left the domain, tumbled or paid
        out too far (`halt_reason` says which)."""
        return self.sim_status is not None and self.sim_status.status == HALTED_OUT_OF_DOMAIN

    @property
    def halt_tau(self):
        """tau at which the simulator halted the run (None if it did not)."""
        return float(self.tau[-1] + self.h) if self.halted and self.h else None

    @property
    def halt_reason(self):
        """Why the simulator halted the run (`halt_reason`); None if it did not."""
        return halt_reason(self.sim_status.message) if self.halted else None

    def describe(self):
        """'run k: steps a-b (N states)', with the simulator's number where it differs."""
        number = f' (simulator run {self.sim_run})' if self.sim_run != self.run else ''
        return (f'run {self.run}{number}: steps {self.step[0]}-{self.step[-1]} '
                f'({self.step.size} states)')


def loop_namespace(state_topics, namespace=None):
    """The namespace of the loop in a bag whose TsrState topics are `state_topics`: the one
    given (ValueError if the bag has no loop there), or the only one recorded (ValueError if
    there are several, or none)."""
    states = sorted(state_topics)
    if namespace is not None:
        wanted = wire.resolve(wire.STATE_TOPIC, namespace)
        if wanted not in states:
            raise ValueError(f'bag has no {wanted} (state topics: {states or "none"})')
        return namespace
    if len(states) > 1:
        raise ValueError(f'bag holds several loops ({states}): give the namespace')
    if not states:
        raise ValueError('bag has no tsr_msgs/msg/TsrState messages')
    return states[0][:-len(wire.STATE_TOPIC)].rstrip('/') or '/'


def given_scale(orbit_rate=None, tether_length=None, mass=None):
    """The units scale of the values given, the paper's for the others; None if none is given
    (then a bag's own, or the paper's, is used). ValueError, one line, for a bad value."""
    given = {name: value for name, value in (('orbit_rate', orbit_rate),
                                             ('tether_length', tether_length), ('mass', mass))
             if value is not None}
    return Scale(**given) if given else None


def reading_options(sample_period=None, orbit_rate=None, tether_length=None, mass=None,
                    match=None):
    """{'scale', 'sample_period', 'match'} as `read_runs` takes them, from the units given
    one by one (`given_scale`); ValueError, one line, for a bad value."""
    check_options(sample_period, match)
    return {'scale': given_scale(orbit_rate, tether_length, mass),
            'sample_period': sample_period, 'match': match}


def state_values(msg):
    """Every field of a TsrState but the header, step and run, as floats (what tells states
    apart)."""
    return np.array([msg.theta, msg.theta_rate, msg.length, msg.length_rate,
                     float(msg.has_out_of_plane), msg.beta, msg.beta_rate], dtype=float)


class _Run:
    """The states of one simulator run: the first message of each step, where each message of
    the step was recorded, and the steps recorded again with other values."""

    def __init__(self, number):
        self.number = number
        self.first = {}            # step -> (order key, decoded TsrState, values)
        self.keys = {}             # step -> order keys of its messages, in recorded order
        self.conflicts = {}        # step -> messages of it with other values than the first
        self.start = None          # order key of its first state

    def add(self, key, msg):
        value = state_values(msg)
        first = self.first.get(msg.step)
        if first is None:
            self.first[msg.step] = (key, msg, value)
            self.keys[msg.step] = [key]
        else:
            self.keys[msg.step].append(key)
            if not np.array_equal(first[2], value, equal_nan=True):
                self.conflicts[msg.step] = self.conflicts.get(msg.step, 0) + 1
        self.start = key if self.start is None else min(self.start, key)

    @property
    def messages(self):
        return sum(len(keys) for keys in self.keys.values())

    @property
    def conflicting(self):
        return sum(self.conflicts.values())

    @property
    def repeats(self):
        """Messages that repeat the first of their step with the same values."""
        return self.messages - len(self.first) - self.conflicting


def split_runs(states):
    """[(order key, decoded TsrState)] in recorded order -> [_Run] in the order of the
    simulator's run numbers (module docstring). ValueError if the states carry no run number."""
    runs = {}
    for key, msg in states:
        number = getattr(msg, 'run', None)
        if number is None:
            raise ValueError('its TsrState messages carry no run number (recorded under an '
                             'older TsrState definition): it cannot be split into runs')
        if number not in runs:
            runs[number] = _Run(number)
        runs[number].add(key, msg)
    return [runs[number] for number in sorted(runs)]


def _owner(runs, step, key):
    """The index of the run a message answering state `step`, recorded at `key`, belongs to."""
    before, after = None, None
    for index, run in enumerate(runs):
        keys = run.keys.get(step)
        if not keys:
            continue
        at = bisect.bisect_right(keys, key)
        if at and (before is None or keys[at - 1] > before[0]):
            before = (keys[at - 1], index)
        elif not at and (after is None or keys[0] < after[0]):
            after = (keys[0], index)
    if before or after:
        return (before or after)[1]
    return _in_progress(runs, key)


def _in_progress(runs, key):
    """The index of the run in progress when `key` was recorded: the one started last before
    it (the first one started, if none had)."""
    started = [(run.start, index) for index, run in enumerate(runs) if run.start <= key]
    return max(started)[1] if started else min((run.start, i) for i, run in enumerate(runs))[1]


def _run_ends(runs):
    """Per run, the order key where the next run (in recorded order) starts (None: the bag's
    end)."""
    starts = sorted(run.start for run in runs)
    return [next((s for s in starts if s > run.start), None) for run in runs]


def check_options(sample_period=None, match=None):
    """ValueError, one line, for a sample period or a match `read_runs` does not take."""
    if match not in (None,) + MATCHES:
        raise ValueError(f"match must be one of {', '.join(MATCHES)}, got {match!r}")
    if sample_period is not None and not (
            isinstance(sample_period, (int, float)) and math.isfinite(sample_period)
            and sample_period > 0):
        raise ValueError('sample_period must be a finite number of seconds > 0, got '
                         f'{sample_period!r}')


def read_loop(path, scale=None, namespace=None, run=None, sample_period=None, match=None):
    """Read the loop of a bag into a `RecordedLoop` (module docstring: runs, how commands are
    matched, units and sample period; `read_runs` takes the same options).

    A bag of several runs is refused (ValueError, one line naming the runs) unless `run` picks
    one: 0 the first."""
    loops = read_runs(path, scale, namespace, sample_period, match)
    what = f'{path} holds {len(loops)} runs of the loop (the simulator was reset): ' + \
        ', '.join(loop.describe() for loop in loops)
    if run is None:
        if len(loops) > 1:
            raise ValueError(f'{what}; read one with read_loop(path, run=k), k in 0..'
                             f'{len(loops) - 1}, or all with read_runs(path)')
        return loops[0]
    if not 0 <= run < len(loops):
        raise ValueError(f'{path} has no run {run}: ' + what.split(': ', 1)[1])
    return loops[run]


def read_runs(path, scale=None, namespace=None, sample_period=None, match=None):
    """Every run of the loop in a bag (module docstring), in order: a list of `RecordedLoop`,
    one for a bag without reset. `scale`: the units of a bag without a simulator RunInfo
    (default the paper's); `sample_period` [s]: its sample period (default from the states'
    stamps); `match`: 'step' or 'time' (default from the simulator's mode). ValueError, one
    line, for a bad option or a bag that cannot be read as a loop; a BagWarning, one line, for
    a bag without commands (its tensions are NaN)."""
    check_options(sample_period, match)
    reader = BagReader(path)
    by_topic, topics_by_type = {}, {}
    for index, (msg, decoded) in enumerate(reader.decoded()):
        by_topic.setdefault(msg.topic, []).append((index, decoded))
        topics_by_type.setdefault(msg.type, set()).add(msg.topic)
    namespace = loop_namespace(topics_by_type.get(STATE_TYPE, ()), namespace)

    def messages(topic):               # in recorded order
        return by_topic.get(wire.resolve(topic, namespace), [])

    run_info = {}
    for _, decoded in messages(wire.RUN_INFO_TOPIC):
        run_info[decoded.role] = yaml.safe_load(decoded.configuration)
    simulator = run_info.get('simulator') or {}
    if 'scale' in simulator:
        scale, units = Scale(**simulator['scale']), UNITS_FROM_RUN_INFO
    else:
        units = UNITS_GIVEN if scale is not None else UNITS_DEFAULT
        scale = scale or Scale()
    match = match or (BY_STEP if simulator.get('mode') == 'lockstep' else BY_TIME)
    try:
        runs = split_runs(messages(wire.STATE_TOPIC))
    except ValueError as error:
        raise ValueError(f'{path}: {error}') from None
    h, h_source = _sample_period(runs, simulator, scale, sample_period)

    commands = messages(wire.TENSION_TOPIC)
    if not commands:
        warnings.warn(f'{path}: no {TENSION_TYPE} on '
                      f'{wire.resolve(wire.TENSION_TOPIC, namespace)}: every tension u is NaN',
                      BagWarning, stacklevel=2)
    statuses = [[] for _ in runs]
    numbers = {run.number: k for k, run in enumerate(runs)}
    for key, decoded in messages(wire.SIM_STATUS_TOPIC):
        if decoded.run in numbers:     # a run none of whose states was recorded: none to tell
            statuses[numbers[decoded.run]].append((key, decoded))
    if match == BY_STEP:
        applied, counts = _by_step(runs, commands)
    else:
        applied, counts = _by_time(runs, commands, statuses)
    excitation, controller = ([{} for _ in runs], [[] for _ in runs])
    for key, decoded in messages(wire.EXCITATION_TOPIC):
        excitation[_owner(runs, decoded.step, key)].setdefault(decoded.step, decoded.tension)
    for key, decoded in messages(wire.CONTROLLER_STATUS_TOPIC):
        controller[_owner(runs, decoded.step, key)].append(decoded)
    loops = []
    for k, run in enumerate(runs):
        counts[k].update(states=run.messages, republished_states=run.repeats,
                         conflicting_states=run.conflicting)
        # Bags recorded before the safety filter's fields decode without them.
        flown = {c.step: (c.flying, c.monitor, getattr(c, 'certificate', ''),
                          getattr(c, 'requested_tension', np.nan))
                 for c in controller[k] if c.status in COMPUTED}
        loops.append(_recorded(run, applied[k], excitation[k], scale, flown, dict(
            namespace=namespace, scale=scale, run_info=run_info, run=k, runs=len(runs),
            sim_run=int(run.number), counts=counts[k], report=reader.report, h=h,
            h_source=h_source, match=match, units=units,
            sim_status=statuses[k][-1][1] if statuses[k] else None,
            controller_status=controller[k][-1] if controller[k] else None,
            compute_time=np.array([c.compute_time for c in controller[k]
                                   if c.status in COMPUTED]))))
    return loops


def _sample_period(runs, simulator, scale, sample_period):
    """(h [tau] or None, where it came from): module docstring."""
    if 'step' in simulator:
        return float(simulator['step']), H_FROM_RUN_INFO
    if sample_period is not None:
        return scale.seconds_to_tau(float(sample_period)), H_FROM_OPTION
    per_step = []
    for run in runs:
        steps = sorted(run.first)
        seconds = [wire.stamp_seconds(run.first[s][1].header.stamp) for s in steps]
        per_step.extend(np.diff(seconds) / np.diff(steps))
    period = float(np.median(per_step)) if per_step else math.nan
    if not (math.isfinite(period) and period > 0.0):
        return None, None
    return scale.seconds_to_tau(period), H_FROM_STAMPS


def _by_step(runs, commands):
    """Per run {step: (tension [N], held)} of the first command answering each step, and the
    counts of its commands (module docstring, 'step')."""
    applied = [{} for _ in runs]
    counts = [dict(commands=0, repeated_commands=0, conflicting_commands=0) for _ in runs]
    orphans = [set() for _ in runs]
    for key, decoded in commands:
        step, tension = decoded.step, decoded.tension
        k = _owner(runs, step, key)
        counts[k]['commands'] += 1
        if step not in runs[k].first:
            orphans[k].add(step)
        if step not in applied[k]:
            applied[k][step] = (tension, False)
        elif applied[k][step][0] == tension or (np.isnan(applied[k][step][0])
                                                and np.isnan(tension)):
            counts[k]['repeated_commands'] += 1
        else:
            counts[k]['conflicting_commands'] += 1
    for count, orphan in zip(counts, orphans):
        count['orphan_commands'] = len(orphan)
    return applied, counts


def _by_time(runs, commands, statuses):
    """Per run {step: (tension [N] in force over the sample from it, held)} and the counts of
    its commands (module docstring, 'time'): a zero-order hold of the commands as recorded."""
    ends = _run_ends(runs)
    keys = [key for key, _ in commands]
    applied, counts = [], []
    for run, end, run_statuses in zip(runs, ends, statuses):
        lo = bisect.bisect_left(keys, run.start)
        hi = len(keys) if end is None else bisect.bisect_left(keys, end)
        # Events of the run in recorded order, each with the tension in force after it.
        events = sorted([(key, 'command', msg) for key, msg in commands[lo:hi]]
                        + [(key, 'status', msg) for key, msg in run_statuses
                           if key >= run.start], key=lambda event: event[0])
        event_keys, in_force, tension, held = [], [], math.nan, False
        for key, kind, msg in events:
            if kind == 'command':
                held = bool(getattr(msg, 'hold', False))
                tension = math.nan if held else msg.tension
            elif msg.holding:
                tension, held = math.nan, True
            event_keys.append(key)
            in_force.append((tension, held))
        steps = sorted(run.first)
        # The tension over the sample from each state: in force when the next state came.
        until = [run.first[s][0] for s in steps[1:]] + [end if end is not None else math.inf]
        run_applied = {}
        for step, key in zip(steps, until):
            at = bisect.bisect_left(event_keys, key)
            run_applied[step] = in_force[at - 1] if at else (math.nan, False)
        applied.append(run_applied)
        counts.append(dict(commands=hi - lo, repeated_commands=0, conflicting_commands=0,
                           orphan_commands=0))
    # Commands recorded before any run started belong to the first one (counted, not applied).
    first = min(range(len(runs)), key=lambda k: runs[k].start)
    counts[first]['commands'] += bisect.bisect_left(keys, runs[first].start)
    return applied, counts


def _recorded(run, applied, excitation, scale, flown, fields):
    steps = np.array(sorted(run.first))
    states = [run.first[s][1] for s in steps.tolist()]
    si = [wire.state_from_msg(msg) for msg in states]
    dim = max(v.size for v in si)
    x = scale.state_from_si(np.array([v[:dim] for v in si]))
    tau = np.array([scale.seconds_to_tau(wire.stamp_seconds(m.header.stamp)) for m in states])
    tension = np.array([applied.get(s, (np.nan, False))[0] for s in steps.tolist()],
                       dtype=float)
    held = np.array([applied.get(s, (np.nan, False))[1] for s in steps.tolist()], dtype=bool)
    u = np.array([scale.tension_to_u(t) for t in tension])
    added = np.array([scale.tension_to_u(excitation.get(s, 0.0)) for s in steps.tolist()])
    conflicting = np.array([s in run.conflicts for s in steps.tolist()], dtype=bool)
    none = ('', '', '', np.nan)
    flying, monitor, certificate = (np.array([flown.get(s, none)[i] for s in steps.tolist()],
                                             dtype=object) for i in (0, 1, 2))
    requested = np.array([scale.tension_to_u(flown.get(s, none)[3]) for s in steps.tolist()],
                         dtype=float)
    return RecordedLoop(step=steps, tau=tau, x=x, u=u, tension=tension, excitation=added,
                        held=held, conflicting=conflicting, flying=flying, monitor=monitor,
                        certificate=certificate, requested=requested, **fields)
