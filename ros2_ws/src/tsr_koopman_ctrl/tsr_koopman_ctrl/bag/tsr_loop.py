"""The deployment loop read back from a bag: the record every figure of a run comes from.

Messages are told apart by type, not by topic name, so a loop recorded under any namespace reads
back; a bag holding more than one loop needs the namespace to pick one.
"""

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

    @property
    def halted(self):
        """True if the simulator stopped because the state left the domain."""
        return self.sim_status is not None and self.sim_status.status == HALTED_OUT_OF_DOMAIN

    @property
    def halt_tau(self):
        """tau at which the state left the domain (None if it did not)."""
        return float(self.tau[-1] + PAPER_STEP) if self.halted else None


def _loop_namespace(topics_by_type, namespace):
    """The namespace of the loop in the bag: given, or the only one recorded."""
    states = sorted(topics_by_type.get(STATE_TYPE, ()))
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


def read_loop(path, scale=None, namespace=None):
    """Read the loop of a bag into a `RecordedLoop`. Republished states count once; the first
    command per step is the one a lockstep simulator applies. The units scale is the one the
    simulator recorded (RunInfo), else `scale`, else the paper's (`tsr_sim.units.Scale()`)."""
    reader = BagReader(path)
    by_topic, topics_by_type = {}, {}
    for msg, decoded in reader.decoded():
        by_topic.setdefault(msg.topic, []).append(decoded)
        topics_by_type.setdefault(msg.type, set()).add(msg.topic)
    namespace = _loop_namespace(topics_by_type, namespace)

    def messages(topic):
        return by_topic.get(wire.resolve(topic, namespace), [])

    run_info = {}
    for decoded in messages(wire.RUN_INFO_TOPIC):
        run_info[decoded.role] = yaml.safe_load(decoded.configuration)
    if 'scale' in run_info.get('simulator', {}):
        scale = Scale(**run_info['simulator']['scale'])
    scale = scale or Scale()
    states, tensions, excitation = {}, {}, {}
    for decoded in messages(wire.STATE_TOPIC):
        states[decoded.step] = (wire.stamp_seconds(decoded.header.stamp),
                                wire.state_from_msg(decoded))
    for decoded in messages(wire.TENSION_TOPIC):
        tensions.setdefault(decoded.step, decoded.tension)
    for decoded in messages(wire.EXCITATION_TOPIC):
        excitation.setdefault(decoded.step, decoded.tension)
    steps = np.array(sorted(states))
    dim = max(states[s][1].size for s in steps)
    x = scale.state_from_si(np.array([states[s][1][:dim] for s in steps]))
    tau = np.array([scale.seconds_to_tau(states[s][0]) for s in steps])
    u = np.array([scale.tension_to_u(tensions.get(s, np.nan)) for s in steps])
    added = np.array([scale.tension_to_u(excitation.get(s, 0.0)) for s in steps])
    sim_status = messages(wire.SIM_STATUS_TOPIC)
    controller = messages(wire.CONTROLLER_STATUS_TOPIC)
    compute = np.array([c.compute_time for c in controller if c.status in COMPUTED])
    return RecordedLoop(step=steps, tau=tau, x=x, u=u, namespace=namespace, scale=scale,
                        run_info=run_info, excitation=added,
                        sim_status=sim_status[-1] if sim_status else None,
                        controller_status=controller[-1] if controller else None,
                        compute_time=compute, report=reader.report)
