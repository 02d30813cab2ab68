"""Simulator node: publishes the TSR state and /clock, takes tension commands, offers reset.

Modes:
  lockstep  advance one step per accepted command answering the current step: deterministic,
            as fast as DDS allows. The first state goes out once `wait_for_subscribers` readers
            of the state topic have matched at the DDS level (the ROS graph can list a reader
            before it can receive). With no command for `republish_period` wall seconds, the
            same state message is published again (a late controller still gets it); the
            controller's answer to that repeat, a copy of the command already accepted, is
            dropped without a word, and so is a command that answers no state (`wire.NO_STEP`:
            the controller's safe tension).
  timed     the rehearsal for hardware: advance at `rate_hz` wall-clock steps per second (time
            scale = rate_hz * step / Omega sim seconds per wall second) holding the latest
            command, whenever it comes. Each run's clock starts as `clock_start` says: by
            default at the first command answering the run's first state (the initial one,
            and after each reset), so the controller's first solve never finds a plant that
            has run on without it; until then that state is published every tick and
            nothing moves. A stop engages the plant's reel hold
            (`Plant.hold_tension`: the reel stopped by its own speed loop, the length then held,
            as a brake would; `hold_gain` 0: `safe_tension` instead): a command with `hold`
            set (the controller was deactivated or shut down, or sees no state), and no valid
            command for `command_timeout` wall seconds (a lost controller: counted). The next
            command without `hold` releases it.

The simulator is the clock: /clock carries the plant's time (t = tau / Omega), from the start
and while it waits, so nodes on sim time start too. Its own timers run on the steady clock, so
it runs with `use_sim_time` true or false. A state that leaves the model's domain or tumbles
(|theta| > `max_swing`) halts the run (status HALTED_OUT_OF_DOMAIN, an ERROR on /diagnostics);
`tsr/reset` starts a new run from step 0, with the next run number (TsrState.run,
SimStatus.run). Its parameters are declared from schema classes (`plant.PlantSettings`,
`node_parameters.SimulatorNodeSettings`, the units' `ScaleSettings`): those that shape the
plant or the run are read-only on a running node; the scheduling ones are applied when set
(`LIVE`).

All maths and command checks are in tsr_sim.plant (ROS-free); this file converts and schedules.
"""

import dataclasses
import sys
import time

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.time import Time
from rosgraph_msgs.msg import Clock
from tsr_msgs.msg import RunInfo, SimStatus, TensionCommand, TsrState
from tsr_msgs.srv import ResetSim

from tsr_sim import dynamics
from tsr_sim.node_parameters import SimulatorNodeSettings
from tsr_sim.plant import config_from_parameters, Plant, PlantSettings, Rejection, Status
from tsr_sim.ros_io import (COMMAND_QOS, declare_schema, declare_scale, Health,
                            LATCHED_QOS, LOOP_PRIORITY, LOOP_PUBLISHER_QOS, MatchedReaders,
                            MatchedWriters, Parameters, run_node, steady_timer)
from tsr_sim.schema import LIVE as APPLIED_LIVE, names_applied
from tsr_sim.wire import (CLOCK_TOPIC, NO_STEP, RESET_SERVICE, RUN_INFO_TOPIC, run_info_msg,
                          scale_dict, SIM_STATUS_TOPIC, STATE_TOPIC, state_to_msg,
                          TENSION_TOPIC)

#: Parameters applied when set on a running simulator (their schemas say so); the others are
#: read-only there.
LIVE = names_applied(APPLIED_LIVE, PlantSettings, SimulatorNodeSettings)
#: Republish periods without the first command of a run before the lockstep simulator warns:
#: a controller's first solve or a late discovery takes a moment, which is no reason to warn.
IDLE_WARNING_PERIODS = 10
#: Seconds the simulator, stopping, waits at most for its readers to acknowledge the last
#: states and status. A recorder that fell behind catches up within one heartbeat period of
#: the writer (3 s in Fast DDS) once it runs again; a reader that never acknowledges (killed,
#: still matched until its lease ends) keeps the simulator no longer than this, which stays
#: under the 10 s a launcher (`launcher.NodeProcess.stop`) grants before it kills.
ACK_TIMEOUT = 8.0


class SimNode(Node):

    NODE_NAME = 'tsr_sim'

    def __init__(self):
        super().__init__(self.NODE_NAME)
        scale = declare_scale(self)
        plant_values = declare_schema(self, PlantSettings)
        own = declare_schema(self, SimulatorNodeSettings, defaults={
            'max_tension': scale.u_to_tension(dynamics.TENSION_LIMIT),
            'safe_tension': scale.u_to_tension(dynamics.EQUILIBRIUM_TENSION)})
        SimulatorNodeSettings(**own)        # the choices (mode, clock_start): one line
        self.mode, self.plant_name = own['mode'], own['plant']
        self.plant = Plant(config_from_parameters(
            {**plant_values, 'max_tension': own['max_tension']}, scale))
        self.scale = self.plant.config.scale
        self.frame_id = own['frame_id']
        self.command_timeout = own['command_timeout']
        self.safe_tension = own['safe_tension']
        self.republish_period = own['republish_period']
        self.progress_every = own['progress_every']
        self.wait_for_subscribers = own['wait_for_subscribers']
        self.exit_on_finish = own['exit_on_finish']
        self.rate_hz = own['rate_hz']
        self.clock_start = own['clock_start']
        self.holding = False        # the reel hold is engaged (timed)
        self.done = False   # run_node stops spinning once set
        self.last_accepted = None   # (step, tension) of the last command accepted in lockstep
        self.accepted_at_start = 0  # commands accepted before this run began
        self.last_state = None      # the state message of the current step, as published

        self.readers = MatchedReaders()
        self.state_pub = self.create_publisher(TsrState, STATE_TOPIC, LOOP_PUBLISHER_QOS,
                                               event_callbacks=self.readers.callbacks)
        self.status_pub = self.create_publisher(SimStatus, SIM_STATUS_TOPIC, LATCHED_QOS)
        self.clock_pub = self.create_publisher(Clock, CLOCK_TOPIC, 10)
        self.writers = MatchedWriters()
        self.create_subscription(TensionCommand, TENSION_TOPIC, self.on_command, COMMAND_QOS,
                                 event_callbacks=self.writers.callbacks)
        self.create_service(ResetSim, RESET_SERVICE, self.on_reset)
        self.create_publisher(RunInfo, RUN_INFO_TOPIC, LATCHED_QOS).publish(run_info_msg(
            self.get_fully_qualified_name(), 'simulator', self.configuration(),
            self.sim_stamp()))

        self.held_tension = self.safe_tension
        self.started = False        # timed: the run's clock has started (`clock_start`)
        self.first_command = None   # timed: the command that started it
        self.command_timeouts = 0
        self.last_command_wall = self.state_published_wall = time.monotonic()
        self.next_idle_warning = 0.0
        self.tick_timer = None
        if self.mode == 'lockstep':
            self.tick_timer = steady_timer(self, self.republish_period, self.on_idle_check)
        else:
            self.get_logger().info(
                f'timed mode: {self.rate_hz} steps/s, time scale '
                f'{self.rate_hz * self.plant.config.step / self.scale.orbit_rate:.1f}x real '
                'time')
            self.tick_timer = steady_timer(self, 1.0 / self.rate_hz, self.on_tick)
        steady_timer(self, 1.0, self.publish_status)
        self.reported = self.counters()
        self.health = Health(self, 'simulator', self.diagnose)
        self.parameters = Parameters(self)
        self.parameters.live('rate_hz', self.set_rate, self.check_timed('rate_hz'))
        self.parameters.live('republish_period', self.set_republish_period,
                             self.check_lockstep('republish_period'))
        self.parameters.live('command_timeout', lambda v: setattr(self, 'command_timeout', v))
        self.parameters.live('safe_tension', self.set_safe_tension, self.check_safe_tension)
        self.parameters.live('progress_every', lambda v: setattr(self, 'progress_every', v))
        self.parameters.live('wait_for_subscribers',
                             lambda v: setattr(self, 'wait_for_subscribers', v))
        self.parameters.live('exit_on_finish', lambda v: setattr(self, 'exit_on_finish', v))
        self.parameters.live('max_steps', self.set_max_steps)
        self.get_logger().info(
            f'{self.mode} simulator, h = {self.plant.config.step} tau '
            f'({self.scale.tau_to_seconds(self.plant.config.step):.2f} s), '
            f'x0 = {self.plant.state.tolist()}, tension unit {self.scale.tension_unit:.4g} N')
        self.publish_clock()
        self.publish_state()
        self.publish_status()

    # Live parameters ----------------------------------------------------------------------

    def check_timed(self, name):
        return lambda value: (None if self.mode == 'timed'
                              else f'only a timed simulator has a {name}')

    def check_lockstep(self, name):
        return lambda value: (None if self.mode == 'lockstep'
                              else f'only a lockstep simulator has a {name}')

    def check_safe_tension(self, value):
        limit = self.plant.config.max_tension
        return None if value <= limit else f'must be <= max_tension ({limit:.4g} N)'

    def set_rate(self, value):
        self.rate_hz = value
        self.restart_timer(1.0 / value, self.on_tick)

    def set_republish_period(self, value):
        self.republish_period = value
        self.restart_timer(value, self.on_idle_check)

    def restart_timer(self, period, callback):
        self.destroy_timer(self.tick_timer)
        self.tick_timer = steady_timer(self, period, callback)

    def set_safe_tension(self, value):
        if self.held_tension == self.safe_tension:      # holding it now: hold the new one
            self.held_tension = value
        self.safe_tension = value

    def set_max_steps(self, value):
        self.plant.config.max_steps = value

    # The loop ------------------------------------------------------------------------------

    def configuration(self):
        """What the bag records about this simulator (RunInfo): the plant and the units."""
        config = self.plant.config
        return {'mode': self.mode, 'plant': self.plant_name, 'step': config.step,
                'substeps': config.substeps, 'initial_state': config.initial_state.tolist(),
                'scale': scale_dict(self.scale), 'max_tension': config.max_tension,
                'max_steps': config.max_steps, 'max_swing': config.max_swing,
                'process_noise_std': list(config.process_noise_std),
                'sensor_noise_std': list(config.sensor_noise_std), 'seed': config.seed,
                'variant': dataclasses.asdict(config.variant)}

    def on_command(self, msg):
        if self.plant.status is not Status.RUNNING:
            return
        step = msg.step if self.mode == 'lockstep' else None
        if step is not None and (step, msg.tension) == self.last_accepted:
            return   # the answer to a republished state: this command was applied already
        if step == NO_STEP:
            # The controller's stop (or safe tension when it saw no state): lockstep waits for
            # the answer to its state, so the plant does not move; the republished state will
            # get one.
            self.get_logger().info(f'lockstep: ignored the stop command {msg.tension:.4g} N '
                                   '(it answers no state)', throttle_duration_sec=5.0)
            return
        if self.mode == 'timed' and not self.started and msg.step != self.plant.step_index:
            return      # a run waits for the answer to its first state, not an older one
        rejection = self.plant.accept(msg.tension, step)
        if rejection is not None:
            self.get_logger().warning(
                f'rejected tension command {msg.tension!r} N for step {msg.step} '
                f'(at step {self.plant.step_index}): {rejection.value}; '
                f'limit [0, {self.plant.config.max_tension:.4g}] N',
                throttle_duration_sec=1.0)
            self.publish_status()
            return
        self.last_command_wall = time.monotonic()
        self.next_idle_warning = 0.0
        self.last_accepted = (step, msg.tension)
        if self.mode == 'lockstep':
            self.step(msg.tension)
            return
        self.first_command = self.first_command or msg
        self.held_tension = msg.tension
        self.set_holding(msg.hold, 'the controller stopped')

    def set_holding(self, holding, why=''):
        """Engage (with the reason) or release the reel hold (timed)."""
        if holding == self.holding:
            return
        self.holding = holding
        if not holding:
            self.get_logger().info('commanded again: hold released')
        elif self.plant.config.hold_gain:
            self.get_logger().warning(f'{why}: reel hold engaged')
        else:
            self.held_tension = self.safe_tension
            self.get_logger().warning(f'{why}: safe tension {self.safe_tension:.4g} N held')
        self.publish_status()

    def on_tick(self):
        if self.plant.status is not Status.RUNNING:
            return
        if not self.started:
            waiting = self.waiting_for()
            if waiting:
                self.get_logger().info(f'timed: waiting for {waiting} before the clock of run '
                                       f'{self.plant.run} starts', throttle_duration_sec=5.0)
                self.last_command_wall = time.monotonic()
                self.publish_clock()
                self.publish_state()
                return
            self.started = True
        if time.monotonic() - self.last_command_wall > self.command_timeout \
                and not self.holding:
            self.command_timeouts += 1
            self.set_holding(True, f'no valid tension command for {self.command_timeout} s')
        self.step(self.held_tension, hold=self.holding)

    def waiting_for(self):
        """Timed: what the run's clock still waits for ('' when nothing: `clock_start`)."""
        if self.clock_start == 'matched' and not self.writers.count:
            return f'a writer of {TENSION_TOPIC} to match'
        if self.clock_start == 'command' and self.first_command is None:
            return f"the first command answering step {self.plant.step_index}"
        return ''

    def on_idle_check(self):
        """Lockstep: publish the state again when its command is late (the first state once
        the loop is wired), and warn when it stays away (at IDLE_WARNING_PERIODS, then every
        10 s)."""
        if self.plant.status is not Status.RUNNING:
            return
        if self.last_state is None:
            self.publish_clock()      # nodes on sim time wait for it before they start
            self.publish_state()
            return
        idle = self.idle_seconds()
        if idle < self.republish_period:
            return
        if idle >= self.warn_after() and time.monotonic() >= self.next_idle_warning:
            self.get_logger().warning(
                f'lockstep: no tension command for step {self.plant.step_index} for '
                f'{idle:.1f} s (is the controller running?)')
            self.next_idle_warning = time.monotonic() + 10.0
        self.state_pub.publish(self.last_state)

    def warn_after(self):
        """Lockstep: seconds without a command before it is a warning. A controller's first
        solve, or its discovery, takes a moment: patience until the first command of a run,
        then a warning after one republish period."""
        periods = 1 if self.plant.accepted > self.accepted_at_start else IDLE_WARNING_PERIODS
        return periods * self.republish_period

    def idle_seconds(self):
        """Lockstep: wall seconds since the current state went out unanswered."""
        return time.monotonic() - max(self.last_command_wall, self.state_published_wall)

    def loop_wired(self):
        return self.readers.count >= self.wait_for_subscribers

    def step(self, tension, hold=False):
        self.plant.advance(tension, hold=hold and bool(self.plant.config.hold_gain))
        if self.plant.status is Status.HALTED_OUT_OF_DOMAIN:
            self.get_logger().error(self.plant.message)
            self.publish_status()
            if self.exit_on_finish:
                self.done = True   # the run is over; the status and the bag say how
            return
        self.publish_clock()
        self.publish_state()
        if self.progress_every and self.plant.step_index % self.progress_every == 0:
            x = self.plant.state
            self.get_logger().info(
                f'tau {self.plant.tau:7.2f}  theta {x[0]:+.4f}  l {x[2] + 1.0:.4f}  '
                f"l' {x[3]:+.4f}  u {self.scale.tension_to_u(tension):.3f}")
        if self.plant.status is Status.FINISHED:
            self.get_logger().info(self.plant.message)
            self.publish_status()
            if self.exit_on_finish:
                self.done = True

    def sim_stamp(self):
        return Time(seconds=self.scale.tau_to_seconds(self.plant.tau)).to_msg()

    def publish_clock(self):
        self.clock_pub.publish(Clock(clock=self.sim_stamp()))

    def publish_state(self):
        """Publish the current step's state (measured once per step: a republished state is
        the same message, so a controller can tell a repeat from a new run)."""
        if self.mode == 'lockstep' and not self.loop_wired():
            self.get_logger().info(
                f'waiting for {self.wait_for_subscribers} readers of {STATE_TOPIC} '
                f'({self.readers.count} matched)', throttle_duration_sec=5.0)
            self.last_state = None
            return
        si = self.scale.state_to_si(self.plant.measure())
        self.last_state = state_to_msg(si, self.plant.step_index, self.sim_stamp(),
                                       self.frame_id, self.plant.run)
        self.state_published_wall = time.monotonic()
        self.state_pub.publish(self.last_state)

    def counters(self):
        return (dict(self.plant.counters), self.command_timeouts)

    def publish_status(self):
        plant = self.plant
        msg = SimStatus(status=int(plant.status), message=plant.message, step=plant.step_index,
                        run=plant.run, holding=self.holding, commands_accepted=plant.accepted,
                        command_timeouts=self.command_timeouts)
        msg.header.stamp = self.sim_stamp()
        for rejection, count in plant.counters.items():
            setattr(msg, f'rejected_{rejection.value}', count)
        self.status_pub.publish(msg)

    def diagnose(self):
        """Health (docs/nodes.md): ERROR when the run halted (the state left the domain or
        tumbled); WARN when commands were rejected or timed out since the last report, while
        the plant holds, or lockstep waits for its readers or a command; OK otherwise."""
        plant = self.plant
        rejected, timeouts = self.counters()
        last_rejected, last_timeouts = self.reported
        self.reported = (rejected, timeouts)
        values = {'status': plant.status.name.lower(), 'mode': self.mode, 'run': plant.run,
                  'step': plant.step_index,
                  'tau': plant.tau, 'commands_accepted': plant.accepted,
                  'command_timeouts': timeouts, 'state_readers': self.readers.count}
        values.update({f'rejected_{r.value}': n for r, n in rejected.items()})
        new = {r.value: rejected[r] - last_rejected[r] for r in Rejection
               if rejected[r] > last_rejected[r]}
        if plant.status is Status.HALTED_OUT_OF_DOMAIN:
            return Health.ERROR, plant.message, values
        if new:
            return Health.WARN, f'commands rejected: {new}', values
        values['holding'] = self.holding
        if timeouts > last_timeouts:
            return Health.WARN, 'no valid command: the plant holds', values
        if self.holding:
            return Health.WARN, 'the controller stopped: the plant holds', values
        if plant.status is Status.RUNNING and self.mode == 'lockstep':
            if not self.loop_wired():
                return Health.WARN, (f'waiting for {self.wait_for_subscribers} readers of '
                                     f'{STATE_TOPIC}'), values
            idle = self.idle_seconds()
            if idle >= self.warn_after():
                return Health.WARN, (f'no command for step {plant.step_index} for '
                                     f'{idle:.1f} s'), values
        return Health.OK, plant.message, values

    def on_reset(self, request, response):
        si = [request.theta, request.theta_rate, request.length, request.length_rate,
              request.beta, request.beta_rate][:self.plant.state.size]
        error = self.plant.reset(self.scale.state_from_si(np.array(si)))
        response.success = error is None
        response.message = error or f'reset to {self.plant.state.tolist()} (dimensionless)'
        if error is None:
            self.get_logger().info(f'reset: {response.message}')
        else:
            self.get_logger().warning(f'reset refused: {error}')
        self.last_command_wall = time.monotonic()
        self.held_tension = self.safe_tension
        self.holding = False
        self.started, self.first_command = False, None    # timed: the new run waits too
        self.last_accepted = None   # step numbers start again
        self.accepted_at_start = self.plant.accepted
        self.publish_status()
        if error is None:
            self.publish_clock()
            self.publish_state()
        return response

    def close(self):
        """Before the node goes (finished, halted or stopped): wait, at most ACK_TIMEOUT s in
        all, until every reliable reader has acknowledged every state and status published.
        A writer destroyed with samples unacknowledged takes them with it: a recorder that had
        not yet received the final state (published just before the exit) never would."""
        if not self.context.ok():
            return
        deadline = time.monotonic() + ACK_TIMEOUT
        for publisher in (self.state_pub, self.status_pub):
            left = Duration(seconds=max(deadline - time.monotonic(), 0.0))
            if not publisher.wait_for_all_acked(left):
                self.get_logger().warning(
                    f'{publisher.topic_name}: not every reader acknowledged the last messages '
                    f'within {ACK_TIMEOUT:g} s; they may lack them')


def main(args=None):
    return run_node(SimNode, on_exit=SimNode.close, args=args, priority=LOOP_PRIORITY)


if __name__ == '__main__':
    sys.exit(main())
