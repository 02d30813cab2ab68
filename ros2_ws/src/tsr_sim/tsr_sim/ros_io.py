"""ROS glue shared by the nodes: QoS, parameter declaration, the node life cycle.

Kept apart from the ROS-free core (dynamics, units, plant, wire) so that the core imports without
rclpy. Topic names and message <-> array conversion are in `tsr_sim.wire`.
"""

import difflib
import signal
import sys
import time

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from tsr_sim.parameter_file import params_file_problem
from tsr_sim.units import DEFAULT_MASS, PAPER_ORBIT_RATE, PAPER_TETHER_LENGTH, Scale

#: State and command: reliable, so lockstep never loses a step; shallow, so no backlog builds.
LOOP_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.VOLATILE)
#: Publishers of the loop keep their last 10 messages for late joiners: a recorder whose reader
#: matches a moment after the first steps (discovery is not symmetric) still records step 0.
#: Loop subscribers stay volatile (LOOP_QOS): a controller or simulator must not act on history.
LOOP_PUBLISHER_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
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


def declare(node, name, default, description, low=None, high=None, step=None):
    """Declare a parameter with a descriptor (and a range for numbers); return its value."""
    descriptor = ParameterDescriptor(description=description)
    if low is not None:
        if isinstance(default, int) and not isinstance(default, bool):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high),
                                                     step=int(step or 1))]
        else:
            descriptor.floating_point_range = [FloatingPointRange(
                from_value=float(low), to_value=float(high), step=float(step or 0.0))]
    return node.declare_parameter(name, default, descriptor).value


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
        close = '.' not in name and difflib.get_close_matches(name, declared, n=1, cutoff=0.8)
        if close:
            node.get_logger().warning(f"parameter '{name}' is not one of this node's and was "
                                      f"ignored (did you mean '{close[0]}'?)")


def declare_scale(node):
    """Declare orbit_rate, tether_length and mass (every node converting units needs them)."""
    return Scale(
        orbit_rate=declare(node, 'orbit_rate', PAPER_ORBIT_RATE, 'Omega [rad/s]', 1e-9, 1.0),
        tether_length=declare(node, 'tether_length', PAPER_TETHER_LENGTH,
                              'full tether length L [m]', 1e-3, 1e9),
        mass=declare(node, 'mass', DEFAULT_MASS, 'robot mass m [kg]', 1e-6, 1e9))


def spin_until_quiet(executor, progress, quiet=0.3, limit=10.0):
    """Spin until `progress()` (a count of work done) has not changed for `quiet` seconds, or
    for at most `limit` seconds: takes what is still queued before a node closes."""
    last, last_change = progress(), time.monotonic()
    deadline = last_change + limit
    while time.monotonic() - last_change < quiet and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.02)
        if progress() != last:
            last, last_change = progress(), time.monotonic()


def run_node(make_node, on_exit=None, args=None, drain=None):
    """The node life cycle every node of the project shares (Jazzy).

    Spins on rclpy's EventsExecutor (measured: a ping-pong ~1.6x and a raw-subscription writer
    ~10x faster than the SingleThreadedExecutor here). rclpy's own signal handlers are off:
    SIGINT and SIGTERM only set a flag, so the context stays up after a signal and
    `drain(node, executor)` can still take what the DDS reader has acknowledged but not yet
    handed over (the recorder's bag then holds every message acknowledged before the stop).
    Then `on_exit(node)` and clean-up; exit code 0. A node whose `done` attribute a callback
    sets ends the run the same way (an exception out of a callback would be logged as fatal).
    A parameter given but not declared that is close to a declared one is a warning
    (`warn_near_misses`). A bad parameter (out of range, wrong type, invalid value) or model
    while constructing, or a --params-file that cannot be read
    (`parameter_file.params_file_problem`, checked before rcl would log its own [ERROR] line),
    is one clear line on stderr and exit code 2.
    """
    from rclpy.experimental import EventsExecutor
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from rclpy.signals import SignalHandlerOptions
    RCLError = rclpy_implementation.RCLError
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
    warn_near_misses(node)
    executor = EventsExecutor()
    executor.add_node(node)
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
