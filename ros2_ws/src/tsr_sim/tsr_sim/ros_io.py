"""ROS glue shared by the nodes: QoS, parameters, health on /diagnostics, the node life cycle.

Kept apart from the ROS-free core (dynamics, units, plant, wire) so that the core imports without
rclpy. Topic names and message <-> array conversion are in `tsr_sim.wire`.

Conventions every node follows here:
- watchdogs and housekeeping timers run on the steady clock (`steady_timer`), so a node works
  with `use_sim_time` true or false: a timer on sim time would wait for a /clock that a stalled
  or absent simulator never sends;
- every parameter is declared from a schema class (`declare_schema`: `tsr_sim.schema`),
  and is either applied live when set or refused with a reason (read-only unless the node
  applies it; `Parameters` checks and applies the live ones);
- health goes out on /diagnostics about once a second (`Health`).
"""

import dataclasses
import os
import signal
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from tsr_sim.node_parameters import ProcessSettings, ScaleSettings
from tsr_sim.parameter_file import params_file_problem
from tsr_sim.schema import AT_START, did_you_mean
from tsr_sim.units import Scale

#: State and command: reliable, so lockstep never loses a step; shallow, so no backlog builds.
LOOP_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
#: A controller's state subscription. The controller takes every state queued at once and
#: answers the newest (a real-time loop drops what it could not answer in time; it counts the
#: gaps), so a deep queue builds no backlog; a queue of one let the next state push a stray one
#: out before the controller had seen it (a non-finite state then left no trace).
STATE_QUEUE_DEPTH = 100
STATE_QOS = QoSProfile(depth=STATE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                       history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
#: Publishers of the loop keep their last messages for late joiners, and enough of them that a
#: recorder falling behind under load (a reliable writer drops what is past its depth, acked or
#: not) loses nothing: at ~1 000 lockstep steps/s, 1 000 messages are a second of slack.
#: Loop subscribers stay volatile (LOOP_QOS): a controller or simulator must not act on history.
LOOP_PUBLISHER_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                                history=HistoryPolicy.KEEP_LAST,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: Commands into the simulator: reliable and keep-all, so a burst (valid or not) is received and
#: counted in full rather than cut to the last few.
COMMAND_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_ALL, durability=DurabilityPolicy.VOLATILE)
#: Status: a late joiner gets the last one.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: RunInfo read by a node that publishes its own too: every publisher's last one, so that
#: another's arriving first does not push the simulator's out before it is read.
RUN_INFO_READER_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                 history=HistoryPolicy.KEEP_LAST,
                                 durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: /diagnostics, as diagnostic_updater publishes it (an absolute name, shared by every node).
DIAGNOSTICS_TOPIC = '/diagnostics'
DIAGNOSTICS_PERIOD = 1.0


def steady_timer(node, period, callback):
    """A timer on the steady clock, whether or not the node uses sim time."""
    return node.create_timer(period, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


#: The largest bounds a parameter descriptor holds: a side a schema leaves open gets these.
INTEGER_BOUND = 2 ** 62
FLOAT_BOUND = sys.float_info.max


def parameter_descriptor(meta, default, read_only):
    """The descriptor of a schema field (`tsr_sim.schema.setting`): its description, its
    choices, read-only or not, and for a number (`default` decides: an int or a float) its
    range, a side left open filled with the largest bound a descriptor holds."""
    descriptor = ParameterDescriptor(description=meta['description'], read_only=read_only)
    if meta.get('choices'):
        descriptor.additional_constraints = f"one of {', '.join(map(str, meta['choices']))}"
    low, high = meta.get('low'), meta.get('high')
    number = isinstance(default, (int, float)) and not isinstance(default, bool)
    if number and (low is not None or high is not None):
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(
                from_value=-INTEGER_BOUND if low is None else int(low),
                to_value=INTEGER_BOUND if high is None else int(high), step=1)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=-FLOAT_BOUND if low is None else float(low),
                to_value=FLOAT_BOUND if high is None else float(high), step=0.0)]
    return descriptor


def declare_schema(node, schema, section='', applied=None, defaults=None):
    """Declare every field of a schema class (`tsr_sim.schema`) as a parameter of `node`,
    named `<section>.<field>` (or `<field>`), with its description and, for a number, its range
    (`parameter_descriptor`). Read-only where the node applies it at start only: setting it on
    a running node is then refused with rcl's 'read-only' reason, not accepted and ignored.
    `applied` (AT_START, AT_CONFIGURE, LIVE) overrides the fields' own. `defaults`: {field: a
    default the node computes (a field declared with None), or a function of the values
    declared before it}. Returns {field: value}, a sequence as a tuple."""
    values = {}
    for field in dataclasses.fields(schema):
        default = (defaults or {}).get(field.name, field.default)
        if callable(default):
            default = default(values)
        if isinstance(default, tuple):
            default = list(default)       # a ROS array
        read_only = (applied or field.metadata.get('applied', AT_START)) == AT_START
        name = f'{section}.{field.name}' if section else field.name
        value = node.declare_parameter(
            name, default, parameter_descriptor(field.metadata, default, read_only)).value
        values[field.name] = tuple(value) if isinstance(value, list) else value
    return values


def given_parameter_names(node):
    """The names of the parameters given to `node` (--params-file, -p), declared or not. rclpy
    keeps them in Node._parameter_overrides only; Jazzy has no public accessor."""
    return set(node._parameter_overrides)


def warn_near_misses(node):
    """Warn of each top-level parameter given to `node` that it does not declare but that is
    close to one it does (`controler`, `mas`): ROS drops it without a word. Others stay quiet:
    a shared `/**` file holds other nodes' parameters. Dotted names are the nodes' own business
    (the controller refuses a misspelt law setting)."""
    declared = [name for name in node.list_parameters([], 0).names if '.' not in name]
    for name in sorted(given_parameter_names(node) - set(declared)):
        hint = '.' not in name and did_you_mean(name, declared, cutoff=0.8)
        if hint:
            node.get_logger().warning(f"parameter '{name}' is not one of this node's and was "
                                      f'ignored{hint}')


def declare_scale(node, applied=None):
    """Declare orbit_rate, tether_length and mass (`ScaleSettings`: every node converting
    units needs them); return the Scale."""
    return Scale(**declare_schema(node, ScaleSettings, applied=applied))


class Parameters:
    """Set-parameter requests on a running node: each name the node applies live has a
    handler `check(value) -> reason or None` and `apply(value)`; `refuse(name) -> reason or
    None` may refuse others for the node's own reason (a lifecycle state). Read-only names
    never get here: rcl refuses them first. Checks run before any value changes, so a request
    is applied whole or not at all."""

    def __init__(self, node, refuse=None):
        self.node, self.refuse, self.handlers = node, refuse, {}
        node.add_on_set_parameters_callback(self.on_set)
        node.add_post_set_parameters_callback(self.on_applied)

    def live(self, name, apply, check=None):
        self.handlers[name] = (check, apply)

    def on_set(self, parameters):
        for parameter in parameters:
            reason = self.refuse(parameter.name) if self.refuse else None
            check = self.handlers.get(parameter.name, (None, None))[0]
            if reason is None and check is not None:
                reason = check(parameter.value)
            if reason:
                return SetParametersResult(successful=False,
                                           reason=f'{parameter.name}: {reason}')
        return SetParametersResult(successful=True)

    def on_applied(self, parameters):
        for parameter in parameters:
            apply = self.handlers.get(parameter.name, (None, None))[1]
            if apply is not None:
                apply(parameter.value)
                self.node.get_logger().info(f'parameter {parameter.name} set to '
                                            f'{parameter.value!r}')


class MatchedReaders:
    """The readers a publisher has matched at the DDS level (its `matched` events), which is
    what delivery depends on. The ROS graph (get_subscription_count) can list a subscription
    before the writer has matched its reader: a message published then never reaches it."""

    def __init__(self):
        self.count = 0
        self.callbacks = PublisherEventCallbacks(matched=self.on_matched)

    def on_matched(self, status):
        self.count = status.current_count


class MatchedWriters:
    """The writers a subscription has matched at the DDS level (its `matched` events)."""

    def __init__(self):
        from rclpy.event_handler import SubscriptionEventCallbacks
        self.count = 0
        self.callbacks = SubscriptionEventCallbacks(matched=self.on_matched)

    def on_matched(self, status):
        self.count = status.current_count


class Health:
    """A node's health on /diagnostics (diagnostic_msgs/DiagnosticArray), once a second on
    the steady clock: `report()` returns (level, message, {key: value}), level one of
    DiagnosticStatus.OK, WARN, ERROR. The status is named '<node's full name>: <task>'."""

    OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR

    def __init__(self, node, task, report, period=DIAGNOSTICS_PERIOD):
        self.node, self.report = node, report
        self.name = f'{node.get_fully_qualified_name()}: {task}'
        self.publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.timer = steady_timer(node, period, self.publish)

    def publish(self):
        level, message, values = with_scheduling(self.node, *self.report())
        status = DiagnosticStatus(level=level, name=self.name, message=message,
                                  hardware_id=self.node.get_name(),
                                  values=[KeyValue(key=str(key), value=_text(value))
                                          for key, value in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.node.get_clock().now().to_msg()
        self.publisher.publish(array)


def scheduling():
    """How the calling thread is scheduled: 'SCHED_FIFO <priority>' or 'normal'."""
    try:
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            return f'SCHED_FIFO {os.sched_getparam(0).sched_priority}'
    except (OSError, AttributeError):
        pass
    return 'normal'


def with_scheduling(node, level, message, values):
    """A health report with the executor thread's scheduling (`scheduling`: the thread that
    publishes it), WARN where the node's `thread_priority` asked for real time and the system
    refused it (a timed loop beside busy processes then misses its period)."""
    now = scheduling()
    asked = (node.get_parameter('thread_priority').value
             if node.has_parameter('thread_priority') else 0)
    if asked and now == 'normal' and level == Health.OK:
        level, message = Health.WARN, (f'thread_priority {asked} refused: running at normal '
                                       'priority')
    return level, message, {**values, 'scheduling': now}


def _text(value):
    if isinstance(value, float):
        return f'{value:.6g}'
    return str(value)


def spin_until_quiet(executor, progress, quiet=0.3, limit=10.0):
    """Spin until `progress()` (a count of work done) has not changed for `quiet` seconds, or
    for at most `limit` seconds: takes what is still queued before a node closes."""
    last, last_change = progress(), time.monotonic()
    deadline = last_change + limit
    while time.monotonic() - last_change < quiet and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.02)
        if progress() != last:
            last, last_change = progress(), time.monotonic()


def usage_requested(args):
    """True if the command line asks for help (-h, --help before any --ros-args)."""
    args = sys.argv[1:] if args is None else list(args)
    own = args[:args.index('--ros-args')] if '--ros-args' in args else args
    return any(arg in ('-h', '--help') for arg in own)


def print_usage(node_class, doc):
    """What `<node> --help` prints: the node's description and how to give parameters (a node
    started for --help would create its bag, its publishers, its DDS participant)."""
    name = getattr(node_class, 'NODE_NAME', node_class.__name__)
    summary = (doc or '').strip().split('\n\n')[0]
    print(f'{summary}\n\nusage: <executable> [--ros-args [-p NAME:=VALUE ...] '
          f'[--params-file FILE] [-r __ns:=/NAMESPACE] [-r __node:=NAME]]\n\n'
          f'Node name {name}. `ros2 param describe` lists every parameter with its '
          'description, range and whether it is read-only; docs/nodes.md has the tables.')


def pin_threads(node, threads):
    """Limit the process's BLAS / OpenMP thread pools to `threads` (its `threads` parameter;
    0: leave them as the environment sets them)."""
    if threads:
        from threadpoolctl import threadpool_limits
        node.thread_limits = threadpool_limits(limits=threads)
    return threads


#: Real-time priority (SCHED_FIFO, 1-99) of a node in the loop, as ros2_control's
#: `thread_priority`: a simulator or controller sharing its cores with busy processes keeps its
#: period (measured: the timed loop at 100 Hz beside two spinning processes drops 281 states
#: and tumbles at normal priority, 16 at FIFO 50, as many as on an idle machine).
LOOP_PRIORITY = 50


def raise_priority(node, priority):
    """Put the node's executor thread under SCHED_FIFO at `priority` (its `thread_priority`
    parameter; 0: normal scheduling; the DDS threads stay at normal priority: all threads at
    FIFO measured no better). Where the system refuses (no CAP_SYS_NICE, no rtprio limit) the
    node runs on at normal priority with a warning, as ros2_control_node does."""
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError) as err:
            node.get_logger().warning(
                f'thread_priority {priority}: real-time scheduling refused ({err}); running '
                'at normal priority, where busy processes beside it delay its steps')
            return 0
    return priority


def run_node(make_node, on_exit=None, args=None, drain=None, start=None, priority=0):
    """The node life cycle every node of the project shares (Jazzy).

    Spins on rclpy's EventsExecutor (measured: a ping-pong ~1.6x and a raw-subscription writer
    ~10x faster than the SingleThreadedExecutor here). rclpy's own signal handlers are off:
    SIGINT and SIGTERM only set a flag, so the context stays up after a signal and
    `drain(node, executor)` can still take what the DDS reader has acknowledged but not yet
    handed over (the recorder's bag then holds every message acknowledged before the stop).
    Then `on_exit(node)` and clean-up; exit code 0. A node whose `done` attribute a callback
    sets ends the run the same way (an exception out of a callback would be logged as fatal).
    A parameter given but not declared that is close to a declared one is a warning
    (`warn_near_misses`). Every node gets the parameters of `ProcessSettings`: `threads`
    (`pin_threads`) and `thread_priority`, default `priority` (`raise_priority`). A bad
    parameter (out of range, wrong type, invalid value) or model while constructing, or a
    --params-file that cannot be read
    (`parameter_file.params_file_problem`, checked before rcl would log its own [ERROR] line),
    is one clear line on stderr and exit code 2; so is an error `start(node)` returns (a
    managed node brought up at start: its failed transition). `-h`/`--help` prints the usage
    and starts nothing.
    """
    from rclpy.experimental import EventsExecutor
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.signals import SignalHandlerOptions
    RCLError = rclpy_implementation.RCLError
    if usage_requested(args):
        print_usage(make_node, getattr(sys.modules.get(make_node.__module__), '__doc__', ''))
        return 0
    problem = params_file_problem(sys.argv if args is None else args)
    if problem:
        print(f'cannot start: {problem}', file=sys.stderr, flush=True)
        return 2
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RCLError as err:     # e.g. a --params-file rcl cannot parse
        print(f'cannot start: {(str(err).splitlines() or [repr(err)])[0]}', file=sys.stderr,
              flush=True)
        return 2
    stop = []
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, frame: stop.append(number))
    try:
        node = make_node()
    except (ValueError, ParameterException, OSError) as err:   # OSError: an output path
        print(f'cannot start: {err}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    try:
        process = declare_schema(node, ProcessSettings, defaults={'thread_priority': priority})
    except ParameterException as err:
        print(f'cannot start: {err}', file=sys.stderr, flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
        return 2
    warn_near_misses(node)
    pin_threads(node, process['threads'])
    raise_priority(node, process['thread_priority'])
    executor = EventsExecutor()
    executor.add_node(node)
    error = start(node) if start is not None else None
    if error:
        print(f'cannot start: {error}', file=sys.stderr, flush=True)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        return 2
    try:
        while not stop and rclpy.ok() and not getattr(node, 'done', False):
            executor.spin_once(timeout_sec=0.1)
        if drain is not None and rclpy.ok():
            drain(node, executor)
    except (SystemExit, ExternalShutdownException):
        pass
    finally:
        if on_exit is not None:
            on_exit(node)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
