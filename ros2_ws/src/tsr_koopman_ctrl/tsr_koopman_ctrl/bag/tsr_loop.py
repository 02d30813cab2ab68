"""The deployment loop read back from a bag: the record every figure of a run comes from.

Messages are told apart by type, not by topic name, so a loop recorded under any namespace reads
back; a bag holding more than one loop needs the namespace to pick one.

Runs. The simulator's reset (`tsr/reset`) restarts the step count at 0 within one bag, so a step
number alone does not name a state. The states are split into runs in the order they were
recorded (log time, then file order): a run ends where the step goes back to one it never had,
or where a step it has comes again with other values. A state that comes again with the same
values is a republication (the lockstep simulator's idle republish, a late joiner's history),
unless the states that follow show it was the identical start of a reset (they differ, or go
past the run's end): they then move to the new run with it. A reset that replays its run
exactly and stops before that run's end cannot be told from a republication (the data agree).

A command, excitation or controller status (each carries the step it answers) belongs to the
run whose state of that step was recorded last before it (a late answer to the previous run
stays there), else to the first run recording that state after it (delivery across topics is
not ordered), else to the run in progress when it was recorded. A simulator status goes to the
run in progress, or to the next one if its step is below what that run had reached (a reset
publishes the new run's status just before its first state). So no command of one run is ever
matched to a state of another. `read_loop` refuses a bag of several runs unless given `run=k`;
`read_runs` returns them all.
"""

import bisect
from dataclasses import dataclass, field

import numpy as np
from tsr_sim import wire
from tsr_sim.dynamics import PAPER_STEP
from tsr_sim.units import Scale
import yaml

from tsr_koopman_ctrl.bag.reader import BagReader, ReadReport

STATE_TYPE = wire.LOOP_TOPIC_TYPES[wire.STATE_TOPIC]
TENSION_TYPE = wire.LOOP_TOPIC_TYPES[wire.TENSION_TOPIC]
SIM_STATUS_TYPE = wire.LOOP_TOPIC_TYPES[wire.SIM_STATUS_TOPIC]
CONTROLLER_STATUS_TYPE = wire.LOOP_TOPIC_TYPES[wire.CONTROLLER_STATUS_TOPIC]
#: tsr_msgs/SimStatus.status of a plant that stopped because the state left the domain.
HALTED_OUT_OF_DOMAIN = 1
#: ControllerStatus.status values that mean a command was computed (and timed).
COMPUTED = (0, 1, 2)


@dataclass
class RecordedLoop:
    """One deployment as recorded. Arrays are per state step, in the paper's variables."""

    step: np.ndarray              # (N,) state steps, ascending, each once
    tau: np.ndarray               # (N,)
    x: np.ndarray                 # (N, n) dimensionless states (republished states count once)
    u: np.ndarray                 # (N,) the first command answering each step, NaN where none
    namespace: str = '/'
    sim_status: object = None     # the last tsr_msgs/SimStatus, decoded
    controller_status: object = None   # the last tsr_msgs/ControllerStatus, decoded
    compute_time: np.ndarray = field(default_factory=lambda: np.zeros(0))   # [s] per command
    report: ReadReport = None
    scale: Scale = None           # the units the dimensionless arrays were converted with
    #: What the nodes ran with ('simulator', 'controller': their RunInfo, parsed): the plant
    #: variant, the law, its settings and model, the units scale.
    run_info: dict = field(default_factory=dict)
    excitation: np.ndarray = None   # (N,) dimensionless tension the controller added per step
    tension: np.ndarray = None    # (N,) [N] the command of `u` as recorded (SI), NaN where none
    run: int = 0                  # which run of the bag this is (a reset starts the next)
    runs: int = 1                 # how many the bag holds
    #: Message counts of the run: states and commands (every message of the run),
    #: republished_states, repeated_commands (identical to the first of their step),
    #: conflicting_commands (differing from it), orphan_commands (steps no state of the run has).
    counts: dict = field(default_factory=dict)

    @property
    def halted(self):
        """True if the simulator stopped because the state left the domain."""
        return self.sim_status is not None and self.sim_status.status == HALTED_OUT_OF_DOMAIN

    @property
    def halt_tau(self):
        """tau at which the state left the domain (None if it did not)."""
        return float(self.tau[-1] + PAPER_STEP) if self.halted else None

    def describe(self):
        """'run k: steps a-b (N states)'."""
        return f'run {self.run}: steps {self.step[0]}-{self.step[-1]} ({self.step.size} states)'


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


def state_values(msg):
    """Every field of a TsrState but the header, as floats (what tells states apart)."""
    return np.array([msg.theta, msg.theta_rate, msg.length, msg.length_rate,
                     float(msg.has_out_of_plane), msg.beta, msg.beta_rate], dtype=float)


class _Run:
    """The states of one run: the first message of each step and where each was recorded."""

    def __init__(self):
        self.first = {}            # step -> (order key, decoded TsrState, values)
        self.keys = {}             # step -> order keys of its messages (first, republished)
        self.last = -1             # highest step
        self.start = None          # order key of its first state

    def add(self, key, msg, value):
        self.first[msg.step] = (key, msg, value)
        self.keys[msg.step] = [key]
        self.last = max(self.last, msg.step)
        self.start = key if self.start is None else min(self.start, key)

    @property
    def repeats(self):
        return sum(len(keys) - 1 for keys in self.keys.values())


def split_runs(states):
    """[(order key, decoded TsrState)] in recorded order -> [_Run] (the module docstring)."""
    runs, chain, previous = [_Run()], [], None
    for key, msg in states:
        step, value = msg.step, state_values(msg)
        run = runs[-1]
        first = run.first.get(step)
        went_back = previous is not None and step < previous
        previous = step
        if first is None:
            if _leads_to(chain, step) or (run.first and step < run.last):
                runs.append(_restart(run, chain, step))
            runs[-1].add(key, msg, value)
            chain = []
        elif np.array_equal(first[2], value, equal_nan=True):
            run.keys[step].append(key)
            if went_back:          # republished, or the start of a reset that repeats the run
                chain = [(key, msg, value)]
            elif chain and step >= chain[-1][1].step:
                chain.append((key, msg, value))
            else:
                chain = []
        else:                      # the step again with other values: a reset
            runs.append(_restart(run, chain, step))
            runs[-1].add(key, msg, value)
            chain = []
    return runs


def _leads_to(chain, step):
    """True if the republished states of `chain` run up to `step`: a reset's identical start."""
    return bool(chain) and chain[-1][1].step in (step - 1, step)


def _restart(run, chain, step):
    """A new run, holding the states of `chain` below `step` if it leads to `step` (taken back
    from `run`, where they were counted as republished)."""
    new = _Run()
    for key, msg, value in chain if _leads_to(chain, step) else ():
        if msg.step >= step:
            continue
        run.keys[msg.step].remove(key)
        if msg.step in new.first:
            new.keys[msg.step].append(key)
        else:
            new.add(key, msg, value)
    return new


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
    """The index of the run in progress when `key` was recorded."""
    starts = [run.start for run in runs]
    return max(bisect.bisect_right(starts, key) - 1, 0)


def _status_owner(runs, step, key):
    """The run a SimStatus (the plant's step when published) belongs to: the one in progress,
    unless its step is below what that run had reached, as at a reset, which publishes the new
    run's status just before its first state."""
    k = _in_progress(runs, key)
    reached = max((s for s, (first, _, _) in runs[k].first.items() if first < key), default=-1)
    return k + 1 if k + 1 < len(runs) and step < reached else k


def read_loop(path, scale=None, namespace=None, run=None):
    """Read the loop of a bag into a `RecordedLoop`. Republished states count once; the first
    command per step is the one a lockstep simulator applies. The units scale is the one the
    simulator recorded (RunInfo), else `scale`, else the paper's (`tsr_sim.units.Scale()`).

    A bag of several runs (a reset, module docstring) is refused (ValueError, one line naming
    the runs) unless `run` picks one: 0 the first."""
    loops = read_runs(path, scale, namespace)
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


def read_runs(path, scale=None, namespace=None):
    """Every run of the loop in a bag (module docstring), in order: a list of `RecordedLoop`,
    one for a bag without reset. Units as `read_loop`."""
    reader = BagReader(path)
    by_topic, topics_by_type = {}, {}
    for index, (msg, decoded) in enumerate(reader.decoded()):
        by_topic.setdefault(msg.topic, []).append(((msg.log_time_ns, index), decoded))
        topics_by_type.setdefault(msg.type, set()).add(msg.topic)
    namespace = loop_namespace(topics_by_type.get(STATE_TYPE, ()), namespace)

    def messages(topic):
        return sorted(by_topic.get(wire.resolve(topic, namespace), []), key=lambda m: m[0])

    run_info = {}
    for _, decoded in messages(wire.RUN_INFO_TOPIC):
        run_info[decoded.role] = yaml.safe_load(decoded.configuration)
    if 'scale' in run_info.get('simulator', {}):
        scale = Scale(**run_info['simulator']['scale'])
    scale = scale or Scale()
    runs = split_runs(messages(wire.STATE_TOPIC))
    tensions, excitation, counts = ([{} for _ in runs] for _ in range(3))
    for count in counts:
        count.update(commands=0, repeated_commands=0, conflicting_commands=0)
    orphans = [set() for _ in runs]
    for key, decoded in messages(wire.TENSION_TOPIC):
        k, step, tension = _owner(runs, decoded.step, key), decoded.step, decoded.tension
        counts[k]['commands'] += 1
        if step not in runs[k].first:
            orphans[k].add(step)
        if step not in tensions[k]:
            tensions[k][step] = tension
        elif tensions[k][step] == tension or np.isnan(tensions[k][step]) and np.isnan(tension):
            counts[k]['repeated_commands'] += 1
        else:
            counts[k]['conflicting_commands'] += 1
    for key, decoded in messages(wire.EXCITATION_TOPIC):
        excitation[_owner(runs, decoded.step, key)].setdefault(decoded.step, decoded.tension)
    sim_status, controller = ([[] for _ in runs] for _ in range(2))
    for key, decoded in messages(wire.SIM_STATUS_TOPIC):
        sim_status[_status_owner(runs, decoded.step, key)].append(decoded)
    for key, decoded in messages(wire.CONTROLLER_STATUS_TOPIC):
        controller[_owner(runs, decoded.step, key)].append(decoded)
    loops = []
    for k, run in enumerate(runs):
        counts[k].update(states=len(run.first) + run.repeats, republished_states=run.repeats,
                         orphan_commands=len(orphans[k]))
        loops.append(_recorded(run, tensions[k], excitation[k], scale, dict(
            namespace=namespace, scale=scale, run_info=run_info, run=k, runs=len(runs),
            counts=counts[k], report=reader.report,
            sim_status=sim_status[k][-1] if sim_status[k] else None,
            controller_status=controller[k][-1] if controller[k] else None,
            compute_time=np.array([c.compute_time for c in controller[k]
                                   if c.status in COMPUTED]))))
    return loops


def _recorded(run, tensions, excitation, scale, fields):
    steps = np.array(sorted(run.first))
    states = [run.first[s][1] for s in steps.tolist()]
    si = [wire.state_from_msg(msg) for msg in states]
    dim = max(v.size for v in si)
    x = scale.state_from_si(np.array([v[:dim] for v in si]))
    tau = np.array([scale.seconds_to_tau(wire.stamp_seconds(m.header.stamp)) for m in states])
    tension = np.array([tensions.get(s, np.nan) for s in steps.tolist()], dtype=float)
    u = np.array([scale.tension_to_u(t) for t in tension])
    added = np.array([scale.tension_to_u(excitation.get(s, 0.0)) for s in steps.tolist()])
    return RecordedLoop(step=steps, tau=tau, x=x, u=u, tension=tension, excitation=added,
                        **fields)
