"""Controller node, a managed (lifecycle) node: answers the newest TSR state with a tension
command for the same step.

Lifecycle (rclpy.lifecycle, as ros2_control and nav2 manage their nodes):
  configure   reads the parameters, loads the model, builds the law (under the runtime-assurance
              supervisor for a learned law), its observer and the excitation, and warms them
              up (`Law.warm_up`: the first command is as fast as the rest); a bad law, setting
              or model fails the transition with one line; publishes the RunInfo the bag keeps
              and creates the command writer (a timed simulator waiting for a commander starts
              its clock once the law is ready)
  activate    starts commanding; within the same run the law resumes (`Law.resume`, no
              reset): its observer keeps the disturbance it learnt and the NMPC re-plans warm
              from its last plan while the plant is where that plan predicted (a re-activation
              with no sample missed flies what the uninterrupted run flies); a plant the hold
              moved off the plan gets a cold start; a new run starts afresh
  deactivate  stops commanding: the node sends the stop (`hold` set, step NO_STEP,
              `safe_tension` for a plant without a hold) once and then nothing until it is
              activated again; a timed simulator or hardware engages its reel hold, which holds
              the tether from any state of a deployment; a lockstep simulator waits
  cleanup     frees the law and its model and removes the command writer
  shutdown    from active, sends the stop first; the process then exits
With `autostart` (default true, as nav2's lifecycle manager brings nodes up) the node configures
and activates itself at start, so `ros2 run` is one command; a failure then stops the process
with one line (exit 2).

The loop as hardware runs it. The node answers the newest state only: at each state it takes
every state queued behind it and answers the newest, so a state superseded while the law
computed is dropped and counted (`dropped_states`) and the law always acts on the plant as it
is now, never on a backlog; the queue is deep (STATE_QUEUE_DEPTH), so that no state, the
simulator's or a stray one, is pushed out of it unseen. Every state queued is checked, in
order. A state that is not finite or that no TSR can be in (`tsr_sim.dynamics.plausible`: a
length <= 0 or past twice the tether, a swing past pi) is refused and counted. Only the
simulator starts a run: a state of another run (`TsrState.run`) starts it when the simulator's
status (tsr/sim_status) reports that run (a reset, a simulator started), when there is no
simulator status (a plant that sends states alone), or once no state of the run flown has come
for `state_timeout` (a restarted simulator; a step back then starts a run too); any other is
not the simulator's (a stray node, a replayed bag) and is refused and counted
(`foreign_states`). A refused state reaches neither the law nor its observer and resets
nothing. (rclpy in Jazzy gives no publisher identity with a message, so a stray state of the
run flown is not told apart from the simulator's.) Within a run, a state older than one
already answered is dropped and counted, and a state repeated exactly (a lockstep simulator
republishes it when its command is late) gets the command it already got, resent. A compute
longer than the period between states is an overrun, counted (not against a lockstep
simulator, which waits for each command: its RunInfo says so). With no state for
`state_timeout` wall seconds the node sends the stop every `state_timeout` seconds until states
return.

SI state in, SI tension out; the law (`tsr_koopman_ctrl.control`) works in the paper's
dimensionless variables, converted through `tsr_sim.units`. Every step goes through
`control.step.ControlStep` (the state checks, the law, the excitation, the clamp to
[0, max_tension], the law told what was sent), the step the ROS-free `closed_loop` takes too.
Commands and statuses carry the stamp of the state they answer, so a bag has one time base.
Each state's outcome, which law flew it and why the supervisor distrusts the learned law, and
the law's compute time go out on `tsr/controller_status`; health on /diagnostics.

Parameters, each declared from a schema class (`tsr_sim.schema`; the node's own:
`controller_parameters.ControllerNodeSettings`): `law` picks the law; every law's settings are
declared as `<law>.<setting>` from its Settings class (the one declaration), with `observer.*`,
`supervisor.*`, `safety_filter.*` and `excitation.*`.
Those and the units scale are read at configure: set them on an unconfigured node (refused
otherwise, with the reason). `max_tension`, `safe_tension`, `state_timeout` and
`wait_for_subscribers` are applied live. A parameter under a law's, `observer.`, `supervisor.`
or `excitation.` section that names no setting there stops the node at start with one line
(ROS would drop it without a word).
"""

from collections import deque
import dataclasses
import math
import sys
import time

import numpy as np
from rclpy.duration import Duration
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from tsr_msgs.msg import ControllerStatus, Excitation, RunInfo, TensionCommand, TsrState
from tsr_sim import dynamics
from tsr_msgs.msg import SimStatus
import yaml
from tsr_sim.ros_io import (declare_schema, declare_scale, given_parameter_names, Health,
                            LATCHED_QOS, LOOP_PRIORITY, LOOP_PUBLISHER_QOS, MatchedReaders,
                            Parameters, RUN_INFO_READER_QOS, run_node, STATE_QOS,
                            STATE_QUEUE_DEPTH, steady_timer)
from tsr_sim.plant import SCALE_PARAMETERS
from tsr_sim.schema import AT_CONFIGURE, LIVE as APPLIED_LIVE, names_applied
from tsr_sim.units import Scale
from tsr_sim.wire import (CONTROLLER_STATUS_TOPIC, EXCITATION_TOPIC, NO_STEP, RUN_INFO_TOPIC,
                          run_info_msg, scale_dict, SIM_STATUS_TOPIC, STATE_TOPIC, state_from_msg,
                          TENSION_TOPIC, tension_msg)

from tsr_koopman_ctrl.control import make_controller, TensionLimiter
from tsr_koopman_ctrl.control.excitation import Excitation as ExcitationSource
from tsr_koopman_ctrl.control.registry import law_class, settings_sections
from tsr_koopman_ctrl.control.settings import fields, unknown_setting_names
from tsr_koopman_ctrl.control.step import ControlStep, Outcome
from tsr_koopman_ctrl.model.model_file import weights_sha256
from tsr_koopman_ctrl.nodes.controller_parameters import ControllerNodeSettings

#: Compute times kept for the median and p99 on /diagnostics.
COMPUTE_WINDOW = 1000
#: Intervals between states kept for the period a compute must fit in (their median).
PERIOD_WINDOW = 50
#: Seconds a leaving node waits for its readers to acknowledge the stop (a bounded exit).
STOP_ACK_TIMEOUT = 2.0
#: Parameters applied when set (their schema says so); the others are read at configure (law,
#: settings, units) or at start (autostart).
LIVE = names_applied(APPLIED_LIVE, ControllerNodeSettings)
#: Lifecycle state ids (lifecycle_msgs/State) and their labels.
UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = 1, 2, 3, 4
STATE_LABELS = {UNCONFIGURED: 'unconfigured', INACTIVE: 'inactive', ACTIVE: 'active',
                FINALIZED: 'finalized'}


def settings_values(node, section, settings_class):
    """{setting: value} of a section as the node's parameters hold it now."""
    values = {}
    for name, default, _ in fields(settings_class):
        value = node.get_parameter(f'{section}.{name}').value
        values[name] = tuple(value) if isinstance(default, tuple) else value
    return values


class ControllerNode(LifecycleNode):

    NODE_NAME = 'tsr_controller'

    def __init__(self):
        super().__init__(self.NODE_NAME)
        # A misspelt setting would be dropped by ROS and the law deployed with its default.
        problems = unknown_setting_names(given_parameter_names(self), settings_sections())
        if problems:
            raise ValueError('; '.join(problems))
        own = declare_schema(self, ControllerNodeSettings)
        for section, settings_class in settings_sections().items():
            declare_schema(self, settings_class, section, applied=AT_CONFIGURE)
        declare_scale(self, applied=AT_CONFIGURE)
        self.autostart = own['autostart']
        self.max_tension, self.safe_tension = own['max_tension'], own['safe_tension']
        self.state_timeout = own['state_timeout']
        self.wait_for_subscribers = own['wait_for_subscribers']
        self.wait_for_status_subscribers = own['wait_for_status_subscribers']
        self.counts = {'commands': 0, 'non_finite_states': 0, 'refused_states': 0,
                       'foreign_states': 0, 'dropped_states': 0, 'overruns': 0,
                       'state_timeouts': 0, 'resent': 0, 'runs': 0}
        self.reported = {'fallbacks': 0, 'non_finite': 0, 'refused': 0, 'foreign': 0}
        self.failure = ''            # why the last configure failed
        self.starting = False
        self.lifecycle_state = UNCONFIGURED
        self.law = self.step = self.limiter = None
        self.scale, self.law_name, self.model_info = Scale(), '', {}
        self.active = False
        self.non_finite_outputs = 0
        self.last_answer = None      # ((step, SI state bytes), command) of the last state answered
        self.run = None              # TsrState.run of the states answered
        self.last_step = None        # the latest step of that run taken
        self.last_state_wall = time.monotonic()
        self.last_state = None       # dimensionless state of the last state taken
        self.refusing = False        # the last state was refused (not finite, no TSR state)
        self.last_refused_wall = 0.0
        self.sim_status = None       # the simulator's last SimStatus (the run it is in, a halt)
        self.compute_seconds = deque(maxlen=COMPUTE_WINDOW)
        self.intervals = deque(maxlen=PERIOD_WINDOW)
        # The command writer exists from configure on (created there, after the law is warm),
        # as a managed node's publishers do: a timed simulator or hardware that waits for a
        # commander starts its clock once the law can answer.
        self.readers = MatchedReaders()
        self.pub = None
        self.status_readers = MatchedReaders()
        self.status_pub = self.create_publisher(ControllerStatus, CONTROLLER_STATUS_TOPIC,
                                                LOOP_PUBLISHER_QOS,
                                                event_callbacks=self.status_readers.callbacks)
        self.excitation_readers = MatchedReaders()
        self.run_info_pub = self.create_publisher(RunInfo, RUN_INFO_TOPIC, LATCHED_QOS)
        self.excitation_pub = None
        self.state_sub = self.create_subscription(TsrState, STATE_TOPIC, self.on_state,
                                                  STATE_QOS)
        self.create_subscription(SimStatus, SIM_STATUS_TOPIC,
                                 lambda msg: setattr(self, 'sim_status', msg), LATCHED_QOS)
        self.plant_waits = False     # the simulator is lockstep (its RunInfo says so)
        self.create_subscription(RunInfo, RUN_INFO_TOPIC, self.on_run_info,
                                 RUN_INFO_READER_QOS)
        self.timeout_timer = steady_timer(self, self.state_timeout, self.check_state_timeout)
        self.health = Health(self, 'controller', self.diagnose)
        self.parameters = Parameters(self, refuse=self.refuse_parameter)
        self.parameters.live('max_tension', self.set_max_tension, self.check_max_tension)
        self.parameters.live('safe_tension', self.set_safe_tension, self.check_safe_tension)
        self.parameters.live('state_timeout', self.set_state_timeout)
        self.parameters.live('wait_for_subscribers',
                             lambda v: setattr(self, 'wait_for_subscribers', v))
        self.parameters.live('wait_for_status_subscribers',
                             lambda v: setattr(self, 'wait_for_status_subscribers', v))

    # Lifecycle -----------------------------------------------------------------------------

    def start(self):
        """With `autostart`: configure and activate; the reason (one line) if that fails."""
        if not self.autostart:
            self.get_logger().info('unconfigured: waiting for a lifecycle manager (autostart '
                                   'is false)')
            return None
        self.starting = True      # a failure is then the one 'cannot start' line
        try:
            if self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
                return self.failure or 'configure failed'
            if self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
                return 'activate failed'
        finally:
            self.starting = False
        return None

    def on_configure(self, state):
        try:
            self.build()
        except (ValueError, OSError) as error:
            self.failure = str(error).splitlines()[0]
            if not self.starting:
                self.get_logger().error(f'configure failed: {self.failure}')
            self.law = self.step = None
            return TransitionCallbackReturn.FAILURE
        self.failure = ''
        self.lifecycle_state = INACTIVE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state):
        # Within the same run the law resumes warm (`Law.resume`: its plan and its observer's
        # disturbance estimate kept); a new run, seen at its first state, starts it afresh.
        self.step.resume()
        self.last_answer = None
        if self.run is not None:
            self.last_step = -1       # the states missed while inactive are no drops
        self.last_state_wall = time.monotonic()
        self.intervals.clear()
        self.active, self.lifecycle_state = True, ACTIVE
        self.get_logger().info(f'active: {self.law_name} commanding')
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state):
        self.active, self.lifecycle_state = False, INACTIVE
        self.publish_stop(ControllerStatus.SAFE_TENSION)
        self.get_logger().info('inactive: stopped commanding (the stop sent: the plant holds; '
                               f'{self.safe_tension:.4g} N for a plant without a hold)')
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state):
        self.law = self.step = None
        self.destroy_publisher(self.pub)
        self.pub = None
        if self.excitation_pub is not None:
            self.destroy_publisher(self.excitation_pub)
            self.excitation_pub = None
        self.lifecycle_state = UNCONFIGURED
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state):
        self.stop_if_active('shut down while active')
        self.active, self.law, self.step = False, None, None
        self.lifecycle_state = FINALIZED
        self.done = True          # run_node ends the process
        return TransitionCallbackReturn.SUCCESS

    def build(self):
        """The law, its observer, the excitation and the clamp from the parameters."""
        self.law_name = self.get_parameter('law').value
        settings_class = law_class(self.law_name).Settings
        settings = settings_class(**settings_values(self, self.law_name, settings_class))
        sections = settings_sections()
        observer = sections['observer'](**settings_values(self, 'observer',
                                                          sections['observer']))
        supervisor = sections['supervisor'](**settings_values(self, 'supervisor',
                                                              sections['supervisor']))
        excitation = ExcitationSource(sections['excitation'](
            **settings_values(self, 'excitation', sections['excitation'])))
        self.scale = Scale(**{name: self.get_parameter(name).value
                              for name in SCALE_PARAMETERS})
        self.limiter = TensionLimiter(self.scale.tension_to_u(self.max_tension))
        safety = sections['safety_filter'](
            **settings_values(self, 'safety_filter', sections['safety_filter']))
        self.law = make_controller(self.law_name, settings, observer, supervisor, safety,
                                   u_max=self.scale.tension_to_u(self.max_tension))
        self.law.warm_up()
        self.step = ControlStep(self.law, self.limiter, excitation)
        self.step.reset()
        self.run = self.last_step = None
        if self.pub is None:
            self.readers = MatchedReaders()
            self.pub = self.create_publisher(TensionCommand, TENSION_TOPIC, LOOP_PUBLISHER_QOS,
                                             event_callbacks=self.readers.callbacks)
        model = self.law.model
        self.model_info = ({} if model is None or not model.path else
                           {'path': model.path, 'weights_sha256': weights_sha256(model.path)})
        # Only an excited controller offers tsr/excitation: a publisher that never sends would
        # look like a broken transport to the recorder's silence check.
        if excitation.active and self.excitation_pub is None:
            self.excitation_readers = MatchedReaders()
            self.excitation_pub = self.create_publisher(
                Excitation, EXCITATION_TOPIC, LOOP_PUBLISHER_QOS,
                event_callbacks=self.excitation_readers.callbacks)
        self.run_info_pub.publish(run_info_msg(
            self.get_fully_qualified_name(), 'controller',
            self.configuration(settings, observer, supervisor, excitation.settings),
            self.get_clock().now().to_msg()))
        self.get_logger().info(f'{self.law_name} controller ({settings}), clamp [0, '
                               f'{self.max_tension:.4g}] N'
                               + (f', model {model.path}' if model is not None else ''))

    def configuration(self, settings, observer, supervisor, excitation):
        """What the bag records about this controller (RunInfo): law, settings, model and its
        weights' hash, units scale, clamp, observer, supervisor, excitation."""
        def plain(values):
            return {k: list(v) if isinstance(v, tuple) else v
                    for k, v in dataclasses.asdict(values).items()}
        config = {'controller': self.law_name, 'settings': plain(settings),
                  'scale': scale_dict(self.scale), 'max_tension': self.max_tension,
                  'observer': plain(observer), 'supervisor': plain(supervisor),
                  'excitation': plain(excitation)}
        if self.model_info:
            config['model'] = dict(self.model_info)
        return config

    # Parameters ----------------------------------------------------------------------------

    def refuse_parameter(self, name):
        configured_by = name == 'law' or name in SCALE_PARAMETERS or name.split('.')[0] in (
            settings_sections())
        if not configured_by or self.lifecycle_state == UNCONFIGURED:
            return None
        return (f'read at configure: the node is {STATE_LABELS[self.lifecycle_state]}; '
                'deactivate and clean it up, set it, then configure again')

    def check_max_tension(self, value):
        if value < self.safe_tension:
            return f'must be >= safe_tension ({self.safe_tension:.4g} N)'
        return None

    def check_safe_tension(self, value):
        if value > self.max_tension:
            return f'must be <= max_tension ({self.max_tension:.4g} N)'
        return None

    def set_max_tension(self, value):
        self.max_tension = value
        if self.limiter is not None:
            self.limiter.u_max = self.scale.tension_to_u(value)
            self.law.limit_tension(self.limiter.u_max)    # its plans, its filter's backups

    def set_safe_tension(self, value):
        self.safe_tension = value

    def set_state_timeout(self, value):
        self.state_timeout = value
        self.destroy_timer(self.timeout_timer)
        self.timeout_timer = steady_timer(self, value, self.check_state_timeout)

    # The loop ------------------------------------------------------------------------------

    def readers_missing(self):
        """What the node still waits for before it answers a state ('' when nothing): the
        readers of its topics, matched at the DDS level (what delivery depends on)."""
        wanted = [(TENSION_TOPIC, self.readers, self.wait_for_subscribers),
                  (CONTROLLER_STATUS_TOPIC, self.status_readers,
                   self.wait_for_status_subscribers)]
        if self.excitation_pub is not None:
            wanted.append((EXCITATION_TOPIC, self.excitation_readers,
                           self.wait_for_status_subscribers))
        return ', '.join(f'{want} readers of {topic} ({readers.count} matched)'
                         for topic, readers, want in wanted if readers.count < want)

    def on_state(self, msg):
        if not self.active:
            return
        missing = self.readers_missing()
        if missing:
            self.get_logger().info(f'waiting for {missing}', throttle_duration_sec=5.0)
            return
        now = time.monotonic()
        newest = None
        for state in self.queued_states(msg):
            admitted = self.admit(state, now)
            if admitted is not None:
                newest = (state, *admitted)
        if newest is not None:
            self.answer(*newest, now)

    def queued_states(self, first):
        """`first` and the states queued behind it, oldest first; at most a queue's worth, so
        that a flood cannot hold the node here."""
        yield first
        # Taken as rclpy's executors take (their events for these then find nothing left).
        handle = self.state_sub.handle
        for _ in range(STATE_QUEUE_DEPTH):
            with handle:
                taken = handle.take_message(TsrState, self.state_sub.raw)
            if taken is None:
                return
            yield taken[0]

    def admit(self, msg, now):
        """(SI state, dimensionless state) of a state the law may take; None for one it must
        not, counted: not finite or no TSR state (`refuse`), or not the simulator's
        (`count_foreign`)."""
        si = state_from_msg(msg, dynamics.PLANAR_DIM)
        x = self.scale.state_from_si(si)
        refused = self.step.check(x)
        if refused is not None:      # before anything else: a stray message changes nothing
            self.refuse(msg, x, refused)
            return None
        if msg.run != self.run and not self.run_started(msg.run, now):
            self.count_foreign(msg)
            return None
        self.refusing = False
        return si, x

    def run_started(self, run, now):
        """Whether the simulator started `run`, the run of a state that is not the run flown:
        its status reports that run, or there is no simulator status (a plant that sends
        states alone), or the run flown has been silent for state_timeout (the simulator was
        restarted)."""
        status = self.sim_status
        return status is None or status.run == run or self.run_silent(now)

    def run_silent(self, now):
        """No state of the run flown answered for state_timeout (the stop is being sent)."""
        return now - self.last_state_wall >= self.state_timeout

    def answer(self, msg, si, x, now):
        """The command for a state admitted: resent for a repeat, none for one older than the
        run's latest; the law's otherwise."""
        key = (msg.run, msg.step, si.tobytes())
        if self.last_answer is not None and self.last_answer[0] == key:
            self.last_state_wall = now
            self.counts['resent'] += 1
            self.pub.publish(self.last_answer[1])
            self.get_logger().info(f'state of step {msg.step} repeated: its command resent',
                                   throttle_duration_sec=5.0)
            return
        elapsed = 1
        if msg.run != self.run:
            self.new_run(msg.run)
        elif msg.step <= self.last_step:
            if self.run_silent(now):
                self.new_run(msg.run)       # a step back after a silence: a new simulator
            else:
                self.counts['dropped_states'] += 1      # older than one taken: out of order
                self.get_logger().warning(f'state of step {msg.step} after step '
                                          f'{self.last_step} of the same run: dropped',
                                          throttle_duration_sec=1.0)
                return
        elif self.last_step >= 0:
            elapsed = msg.step - self.last_step
            self.counts['dropped_states'] += elapsed - 1       # superseded while computing
            self.intervals.append((now - self.last_state_wall) / elapsed)
        self.last_state_wall = now
        self.last_step, self.last_state = msg.step, x
        result = self.step(x, elapsed)
        self.compute_seconds.append(result.compute_seconds)
        if (self.intervals and not self.plant_waits
                and result.compute_seconds > np.median(self.intervals)):
            self.counts['overruns'] += 1
        if result.outcome is Outcome.NON_FINITE_OUTPUT:
            self.non_finite_outputs += 1
            self.get_logger().error(f'{self.law_name} gave a non-finite tension at step '
                                    f'{msg.step}: no command', throttle_duration_sec=1.0)
            self.publish_status(msg.step, msg.header.stamp, int(result.outcome),
                                result.compute_seconds)
            return
        stamp = msg.header.stamp      # the answer carries the time of the state it answers
        if self.excitation_pub is not None:
            excitation = Excitation(step=msg.step,
                                    tension=self.scale.u_to_tension(result.excitation))
            excitation.header.stamp = stamp
            self.excitation_pub.publish(excitation)
        tension = self.scale.u_to_tension(result.tension)
        command = tension_msg(tension, msg.step, stamp)
        self.pub.publish(command)
        self.last_answer = (key, command)
        self.counts['commands'] += 1
        self.publish_status(msg.step, stamp, int(result.outcome), result.compute_seconds,
                            tension, self.scale.u_to_tension(self.law.requested),
                            self.law.certificate)

    def on_run_info(self, msg):
        """A lockstep simulator waits for each command: the period between its states is the
        loop's own, so no compute overruns it (a timed simulator or hardware keeps its
        period whatever the controller does)."""
        if msg.role == 'simulator':
            try:
                mode = (yaml.safe_load(msg.configuration) or {}).get('mode')
            except (yaml.YAMLError, AttributeError):
                mode = None
            self.plant_waits = mode == 'lockstep'

    def refuse(self, msg, x, outcome):
        """A state the law must not see (not finite, or no TSR state): counted, no command;
        the run's step count is left as it was (a stray message is no step of it)."""
        name = 'non_finite_states' if outcome is Outcome.NON_FINITE_STATE else 'refused_states'
        self.counts[name] += 1
        self.refusing, self.last_refused_wall = True, time.monotonic()
        self.get_logger().warning(
            f"{'non-finite state' if name == 'non_finite_states' else 'no TSR state'} at "
            f'step {msg.step} ({x.tolist()}, dimensionless): refused, no command',
            throttle_duration_sec=1.0)
        self.publish_status(msg.step, msg.header.stamp, int(outcome))

    def count_foreign(self, msg):
        """A state of a run the simulator did not start: another publisher's (a stray node, a
        replayed bag). Counted, no command, no status (it is no step of the run)."""
        self.counts['foreign_states'] += 1
        self.get_logger().warning(
            f'state of run {msg.run} (step {msg.step}) while the simulator is in run '
            f"{self.sim_status.run}: not the simulator's, refused", throttle_duration_sec=1.0)

    def new_run(self, run):
        """The simulator started a run (`run_started`, or it came back after a silence): the
        law, its observer and the excitation start afresh."""
        if self.run is not None:
            self.counts['runs'] += 1
            self.step.reset()
            self.get_logger().info(f'new run {run} (after run {self.run}): law, observer and '
                                   'excitation reset')
        self.run, self.last_step, self.last_answer = run, -1, None
        self.intervals.clear()

    def publish_status(self, step, stamp, status, compute_time=math.nan, tension=math.nan,
                       requested=math.nan, certificate=''):
        law = self.law
        msg = ControllerStatus(step=int(step), status=int(status),
                               controller=self.law_name,
                               flying=law.flying if law else '',
                               monitor=law.monitor if law else '',
                               certificate=certificate,
                               compute_time=float(compute_time), tension=float(tension),
                               requested_tension=float(requested),
                               commands=int(self.counts['commands']),
                               clamped=int(self.limiter.clamped if self.limiter else 0),
                               solver_fallbacks=int(law.fallbacks if law else 0),
                               non_finite_states=int(self.counts['non_finite_states']),
                               state_timeouts=int(self.counts['state_timeouts']),
                               refused_states=int(self.counts['refused_states']),
                               dropped_states=int(self.counts['dropped_states']),
                               overruns=int(self.counts['overruns']),
                               supervisor_switches=int(law.switches if law else 0),
                               safety_corrections=int(law.corrections if law else 0))
        msg.header.stamp = stamp
        self.status_pub.publish(msg)

    def publish_stop(self, status):
        """The stop: `hold` set, answering no state (step NO_STEP), `safe_tension` for a plant
        without a hold; and its status."""
        stamp = self.get_clock().now().to_msg()
        self.pub.publish(tension_msg(self.safe_tension, NO_STEP, stamp, hold=True))
        self.publish_status(NO_STEP, stamp, status, tension=self.safe_tension)

    def check_state_timeout(self):
        if not self.active or time.monotonic() - self.last_state_wall < self.state_timeout:
            return
        self.counts['state_timeouts'] += 1
        self.get_logger().warning(f'no state for {self.state_timeout:g} s: the stop sent (the '
                                  'plant holds)', throttle_duration_sec=5.0)
        self.publish_stop(ControllerStatus.SAFE_TENSION)

    # Health --------------------------------------------------------------------------------

    def diagnose(self):
        """Health (docs/nodes.md): ERROR when configure failed, the law gave a non-finite
        tension, a state was refused since the last report or refused states keep coming
        (ERROR while the fault lasts; not for state_timeout: that is the stale-input
        warning), the plant is tumbling (|theta| past the tumbling swing) or the
        simulator halted the run; WARN when not active, when states not the simulator's were
        refused since the last report, while the supervisor's fallback flies, when the law's
        solver fell back, states were dropped or computes overran since the last report, or no
        state came for state_timeout; OK otherwise."""
        law = self.law
        fallbacks = law.fallbacks if law else 0
        values = {'lifecycle_state': STATE_LABELS[self.lifecycle_state],
                  'law': self.law_name or self.get_parameter('law').value,
                  'run': '' if self.run is None else self.run}
        values.update({f'model_{k}': v for k, v in self.model_info.items()})
        if self.compute_seconds:
            times = np.array(self.compute_seconds) * 1e3
            values.update(compute_median_ms=float(np.median(times)),
                          compute_p99_ms=float(np.percentile(times, 99)))
        if self.intervals:
            values['period_ms'] = float(np.median(self.intervals)) * 1e3
        values.update(self.counts, fallbacks=fallbacks, non_finite_outputs=self.non_finite_outputs,
                      clamped=self.limiter.clamped if self.limiter else 0,
                      last_step=self.last_answer[1].step if self.last_answer else '',
                      last_tension=self.last_answer[1].tension if self.last_answer else '')
        if law is not None:
            values.update(law.diagnostics())
        new = {'fallbacks': fallbacks, 'non_finite': self.non_finite_outputs,
               'refused': self.counts['non_finite_states'] + self.counts['refused_states'],
               'foreign': self.counts['foreign_states'],
               'late': self.counts['dropped_states'] + self.counts['overruns']}
        grown = {k for k, v in new.items() if v > self.reported.get(k, 0)}
        self.reported = new
        x, status = self.last_state, self.sim_status
        if self.failure:
            return Health.ERROR, f'configure failed: {self.failure}', values
        if 'non_finite' in grown:
            return Health.ERROR, 'the law gave a non-finite tension', values
        refusing = (self.refusing
                    and time.monotonic() - self.last_refused_wall < self.state_timeout)
        if refusing or 'refused' in grown:
            return Health.ERROR, 'states refused (not finite, or no TSR state): no command', \
                values
        if status is not None and status.status == SimStatus.HALTED_OUT_OF_DOMAIN:
            return Health.ERROR, f'the simulator halted: {status.message}', values
        if x is not None and abs(x[dynamics.THETA]) > dynamics.TUMBLING_SWING:
            return Health.ERROR, 'the robot is tumbling', values
        if not self.active:
            return Health.WARN, f'{STATE_LABELS[self.lifecycle_state]}: not commanding', values
        if 'foreign' in grown:
            return Health.WARN, (f"{self.counts['foreign_states']} states not the simulator's "
                                 'refused (of a run it did not start)'), values
        if law is not None and law.flying == 'fallback':
            return Health.WARN, f'the fallback law flies (monitor: {law.monitor or "trusted"})', \
                values
        if 'fallbacks' in grown:
            return Health.WARN, "the law's solver fell back", values
        if 'late' in grown:
            return Health.WARN, 'late: states dropped or computes over the period', values
        if time.monotonic() - self.last_state_wall >= self.state_timeout:
            return Health.WARN, f'no state for {self.state_timeout:g} s: the stop sent', values
        return Health.OK, 'commanding', values

    def stop_if_active(self, why):
        """An active controller leaving: the stop, so the plant holds now and not at its
        command timeout. The node waits (at most STOP_ACK_TIMEOUT) until every reader has
        acknowledged it: a writer destroyed before then takes the stop with it."""
        if self.active and self.pub is not None:
            self.publish_stop(ControllerStatus.SAFE_TENSION)
            self.active = False
            status = self.sim_status
            if status is not None and status.status != SimStatus.RUNNING:
                # A finished or halted run has no plant to hold (and its simulator may be
                # gone already, its reader never to acknowledge).
                self.get_logger().info(f'{why}: the stop sent (the run had ended)')
            elif self.pub.wait_for_all_acked(Duration(seconds=STOP_ACK_TIMEOUT)):
                self.get_logger().info(f'{why}: the stop sent and acknowledged')
            else:
                self.get_logger().warning(f'{why}: the stop sent, not acknowledged within '
                                          f'{STOP_ACK_TIMEOUT:g} s (a reader gone or '
                                          'unreachable: the plant holds at its own timeout)')

    def close(self):
        """Process exit (a signal, or `done`): the stop first, as a shutdown transition."""
        self.stop_if_active('stopped by a signal while active')
        self.report()

    def report(self):
        """A closing line for people reading the log (tools read the bag, not this)."""
        if self.compute_seconds:
            times = np.array(self.compute_seconds) * 1e6
            print(f'[tsr_controller] {self.counts["commands"]} commands, compute median '
                  f'{np.median(times):.1f} us, p99 {np.percentile(times, 99):.1f} us (last '
                  f'{len(times)}), clamped {self.limiter.clamped if self.limiter else 0}, '
                  f'solver fallbacks {self.law.fallbacks if self.law else 0}, non-finite '
                  f'states {self.counts["non_finite_states"]}, refused states '
                  f'{self.counts["refused_states"]}, foreign states '
                  f'{self.counts["foreign_states"]}, dropped states '
                  f'{self.counts["dropped_states"]}, overruns {self.counts["overruns"]}, state '
                  f'timeouts {self.counts["state_timeouts"]}, repeated states resent '
                  f'{self.counts["resent"]}, supervisor switches '
                  f'{self.law.switches if self.law else 0}', flush=True)


def main(args=None):
    return run_node(ControllerNode, on_exit=ControllerNode.close, args=args,
                    start=ControllerNode.start, priority=LOOP_PRIORITY)


if __name__ == '__main__':
    sys.exit(main())
