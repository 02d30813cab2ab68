"""The wire, ROS-free: topic names and message <-> array conversion, one home for both.

Every process on the loop (simulator, controller, recorder), the bag reader, the tools and the
tests use these names and these conversions. Names are relative, so they resolve in the node's
namespace (``--ros-args -r __ns:=/tsr1`` moves a whole loop); /clock is global by ROS convention.
Conversions take any object with the message's fields: the generated rclpy classes and the
messages the bag reader decodes alike. Units on the wire are SI (REP 103); `tsr_sim.units` is the
one place that converts to the paper's dimensionless variables.
"""

import numpy as np

from tsr_sim.dynamics import BETA, BETA_RATE, PLANAR_DIM, SPATIAL_DIM

STATE_TOPIC = 'tsr/state'
TENSION_TOPIC = 'tsr/tension_cmd'
SIM_STATUS_TOPIC = 'tsr/sim_status'
CONTROLLER_STATUS_TOPIC = 'tsr/controller_status'
RUN_INFO_TOPIC = 'tsr/run_info'
EXCITATION_TOPIC = 'tsr/excitation'
CLOCK_TOPIC = '/clock'
RESET_SERVICE = 'tsr/reset'

#: TsrState.header.frame_id: the orbital frame the message's angles are measured in (the local
#: vertical and the orbit plane), the simulator's `frame_id` parameter by default.
STATE_FRAME = 'orbit'

#: TensionCommand.step of a command that answers no state: the controller's safe tension, sent
#: when no state comes (the largest uint64, which no state's step reaches). A lockstep
#: simulator ignores it and waits for the answer to its state; a timed one, or hardware,
#: applies it. Not a constant of the message: that would change its definition, and the bag
#: reader refuses bags recorded under another one.
NO_STEP = 2**64 - 1

#: The loop's topics and their types: what the recorder records by default (subscribed at start
#: so nothing is missed) and what the bag reader expects.
LOOP_TOPIC_TYPES = {
    STATE_TOPIC: 'tsr_msgs/msg/TsrState',
    TENSION_TOPIC: 'tsr_msgs/msg/TensionCommand',
    SIM_STATUS_TOPIC: 'tsr_msgs/msg/SimStatus',
    CONTROLLER_STATUS_TOPIC: 'tsr_msgs/msg/ControllerStatus',
    RUN_INFO_TOPIC: 'tsr_msgs/msg/RunInfo',
    EXCITATION_TOPIC: 'tsr_msgs/msg/Excitation',
    CLOCK_TOPIC: 'rosgraph_msgs/msg/Clock',
}
#: Loop topics whose publishers keep their last message for late joiners (transient local):
#: the recorder subscribes to them transient local too, so it has them whenever it started.
LATCHED_TOPICS = (SIM_STATUS_TOPIC, RUN_INFO_TOPIC)


def resolve(name, namespace='/'):
    """The absolute name of `name` for a node in `namespace` (no remapping): what rclpy's
    ``Node.resolve_topic_name`` gives, for readers that have no node (the bag reader, tools)."""
    if name.startswith('/'):
        return name
    parts = namespace.strip('/')
    return f'/{parts}/{name}' if parts else f'/{name}'


def stamp_seconds(stamp):
    """builtin_interfaces/Time -> seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def state_from_msg(msg, dim=None):
    """TsrState -> SI state array, layout of `tsr_sim.units.Scale.state_to_si`.

    `dim` None: 6 components when the message carries the out-of-plane angle, else 4.
    """
    if dim is None:
        dim = SPATIAL_DIM if msg.has_out_of_plane else PLANAR_DIM
    values = [msg.theta, msg.theta_rate, msg.length, msg.length_rate]
    if dim == SPATIAL_DIM:
        values += [msg.beta, msg.beta_rate]
    return np.array(values, dtype=float)


def state_to_msg(si_state, step, stamp, frame_id=STATE_FRAME, run=0):
    """SI state array (4 or 6 components) of step `step` of run `run` -> TsrState."""
    from tsr_msgs.msg import TsrState
    msg = TsrState()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.step = int(step)
    msg.run = int(run)
    msg.theta, msg.theta_rate, msg.length, msg.length_rate = (float(v) for v in si_state[:4])
    if si_state.shape[-1] == SPATIAL_DIM:
        msg.has_out_of_plane = True
        msg.beta, msg.beta_rate = float(si_state[BETA]), float(si_state[BETA_RATE])
    return msg


def tension_msg(tension, step, stamp, hold=False):
    """Tension [N] answering state `step` (NO_STEP: none) -> TensionCommand; `hold`: the
    controller stopped, the plant holds the tether (`tension` for a plant without a hold)."""
    from tsr_msgs.msg import TensionCommand
    msg = TensionCommand()
    msg.header.stamp = stamp
    msg.step = int(step)
    msg.tension = float(tension)
    msg.hold = bool(hold)
    return msg


def run_info_msg(node_name, role, configuration, stamp):
    """A node's configuration (a dict, written as YAML) -> RunInfo."""
    import yaml
    from tsr_msgs.msg import RunInfo
    msg = RunInfo(node=node_name, role=role,
                  configuration=yaml.safe_dump(configuration, sort_keys=False))
    msg.header.stamp = stamp
    return msg


def scale_dict(scale):
    """The units scale as recorded in a RunInfo (tsr_sim.units.Scale fields, SI)."""
    return {'orbit_rate': scale.orbit_rate, 'tether_length': scale.tether_length,
            'mass': scale.mass}
