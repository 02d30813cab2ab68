"""Controller node: answers every TSR state with a tension command for the same step.

SI state in, SI tension out; the law (`tsr_koopman_ctrl.control`) works in the paper's
dimensionless variables, converted through `tsr_sim.units`. Parameters: `controller` picks the
law, whose settings are declared as `<law>.<setting>` from the law's Settings class (the one
declaration; `ros2 param describe` shows descriptions and ranges). Every command is clamped to
[0, max_tension] (the law's own bound is the same number) and the clamps counted. A non-finite
state gets no command. With no state for `state_timeout` wall seconds the node publishes
`safe_tension` (default: the equilibrium tension, u = 3) every `state_timeout` seconds, until
states return. It answers no state, so its step is `tsr_sim.wire.NO_STEP`: a lockstep
simulator ignores it, and a bag reader cannot take it for a step's command (stamped with the
last step, the one sent before any state passed for step 0's answer). A state repeated exactly
(same step, same values: a lockstep simulator publishes the state again when its command is
late, e.g. behind a slow first solve) gets the command it already got, resent, without running
the law again: a second compute would advance the law's plan and observer twice for one step.
Each state's outcome and the law's compute time go out on `tsr/controller_status` (recorded in
the bag). A bad law, setting or model stops the node at start with one line (exit 2), and so
does a parameter under a law's, `observer.` or `excitation.` that names no setting there (ROS
would drop it without a word); parameters of other sections are left to the nodes they are for.
"""

from collections import deque
import dataclasses
import hashlib
import math
import os
import sys
import time

import numpy as np
from rclpy.node import Node
from tsr_msgs.msg import ControllerStatus, Excitation, RunInfo, TensionCommand, TsrState
from tsr_sim import dynamics
from tsr_sim.ros_io import (declare, declare_scale, given_parameter_names, LATCHED_QOS,
                            LOOP_PUBLISHER_QOS, LOOP_QOS, run_node)
from tsr_sim.wire import (CONTROLLER_STATUS_TOPIC, EXCITATION_TOPIC, NO_STEP, RUN_INFO_TOPIC,
                          run_info_msg, scale_dict, STATE_TOPIC, state_from_msg, TENSION_TOPIC,
                          tension_msg)

from tsr_koopman_ctrl.control import CONTROLLERS, make_controller, TensionLimiter
from tsr_koopman_ctrl.control.excitation import Excitation as ExcitationSource
from tsr_koopman_ctrl.control.excitation import ExcitationSettings
from tsr_koopman_ctrl.control.offset_free import ObserverSettings
from tsr_koopman_ctrl.control.registry import law_class, settings_sections
from tsr_koopman_ctrl.control.settings import fields, unknown_setting_names
from tsr_koopman_ctrl.model.model_file import WEIGHTS_FILE

DEFAULT_CONTROLLER = 'koopman_mpc'


def declare_law_settings(node, settings_class, law):
    """Declare `<law>.<setting>` for every setting of the law; return {setting: value}."""
    values = {}
    for name, default, meta in fields(settings_class):
        scalar = not isinstance(default, tuple)
        value = declare(node, f'{law}.{name}', default if scalar else list(default),
                        meta['description'], *((meta['low'], meta['high']) if scalar
                                               and meta['low'] is not None
                                               and meta['high'] is not None else ()))
        values[name] = value if scalar else tuple(value)
    return values


class ControllerNode(Node):

    def __init__(self):
        super().__init__('tsr_controller')
        # A misspelt setting would be dropped by ROS and the law deployed with its default.
        problems = unknown_setting_names(given_parameter_names(self), settings_sections())
        if problems:
            raise ValueError('; '.join(problems))
        self.law_name = declare(self, 'controller', DEFAULT_CONTROLLER,
                                f'control law: one of {sorted(CONTROLLERS)}')
        settings_class = law_class(self.law_name).Settings
        settings = settings_class(**declare_law_settings(self, settings_class, self.law_name))
        self.scale = declare_scale(self)
        max_tension = declare(self, 'max_tension',
                              self.scale.u_to_tension(dynamics.TENSION_LIMIT),
                              f'output clamp [N] (default: u = {dynamics.TENSION_LIMIT:g})',
                              1e-9, 1e9)
        self.limiter = TensionLimiter(self.scale.tension_to_u(max_tension))
        self.observer_settings = ObserverSettings(**declare_law_settings(
            self, ObserverSettings, 'observer'))
        self.controller = make_controller(self.law_name, settings, self.observer_settings,
                                          u_max=self.limiter.u_max)
        self.excitation = ExcitationSource(ExcitationSettings(**declare_law_settings(
            self, ExcitationSettings, 'excitation')))
        self.safe_tension = declare(
            self, 'safe_tension', self.scale.u_to_tension(dynamics.EQUILIBRIUM_TENSION),
            'published when no state arrives for state_timeout [N] (default: u = 3, which '
            'holds the deployed equilibrium)', 0.0, max_tension)
        self.state_timeout = declare(self, 'state_timeout', 5.0, 'wall seconds without a state '
                                     'before safe_tension is published', 0.01, 3600.0)
        self.wait_for_subscribers = declare(
            self, 'wait_for_subscribers', 0, 'send no command until the tension topic has this '
            'many subscribers (simulator, recorder)', 0, 1000)
        self.counts = {'commands': 0, 'non_finite_states': 0, 'state_timeouts': 0,
                       'resent': 0}
        #: ((step, SI state bytes), command) of the last state answered: a repeat is resent.
        self.last_answer = None
        self.last_state_wall = time.monotonic()
        self.compute_seconds = deque(maxlen=100_000)
        self.pub = self.create_publisher(TensionCommand, TENSION_TOPIC, LOOP_PUBLISHER_QOS)
        self.status_pub = self.create_publisher(ControllerStatus, CONTROLLER_STATUS_TOPIC,
                                                LOOP_PUBLISHER_QOS)
        # Only an excited controller offers tsr/excitation: a publisher that never sends would
        # look like a broken transport to the recorder's silence check.
        self.excitation_pub = (self.create_publisher(Excitation, EXCITATION_TOPIC,
                                                     LOOP_PUBLISHER_QOS)
                               if self.excitation.active else None)
        self.create_publisher(RunInfo, RUN_INFO_TOPIC, LATCHED_QOS).publish(run_info_msg(
            self.get_fully_qualified_name(), 'controller', self.configuration(settings),
            self.get_clock().now().to_msg()))
        self.create_subscription(TsrState, STATE_TOPIC, self.on_state, LOOP_QOS)
        self.create_timer(self.state_timeout, self.check_state_timeout)
        model = getattr(self.controller, 'model', None)
        self.get_logger().info(f'{self.law_name} controller ({settings}), clamp [0, '
                               f'{max_tension:.4g}] N'
                               + (f', model {model.path}' if model is not None else ''))

    def on_state(self, msg):
        if self.pub.get_subscription_count() < self.wait_for_subscribers:
            self.get_logger().info(f'waiting for {self.wait_for_subscribers} subscribers to '
                                   f'{TENSION_TOPIC}', throttle_duration_sec=5.0)
            return
        self.last_state_wall = time.monotonic()
        si = state_from_msg(msg, dynamics.PLANAR_DIM)
        key = (msg.step, si.tobytes())
        if self.last_answer is not None and self.last_answer[0] == key:
            self.counts['resent'] += 1
            self.pub.publish(self.last_answer[1])
            self.get_logger().info(f'state of step {msg.step} repeated: its command resent',
                                   throttle_duration_sec=5.0)
            return
        if not np.all(np.isfinite(si)):
            self.counts['non_finite_states'] += 1
            self.get_logger().warning(f'non-finite state at step {msg.step}: no command',
                                      throttle_duration_sec=1.0)
            self.publish_status(msg.step, ControllerStatus.NON_FINITE_STATE)
            return
        fallbacks = self.controller.fallbacks
        start = time.perf_counter()
        u = self.controller.compute(self.scale.state_from_si(si))
        elapsed = time.perf_counter() - start
        self.compute_seconds.append(elapsed)
        if not math.isfinite(u):
            self.get_logger().error(f'controller gave u = {u} at step {msg.step}: no command',
                                    throttle_duration_sec=1.0)
            self.publish_status(msg.step, ControllerStatus.NON_FINITE_OUTPUT, elapsed)
            return
        clamped = self.limiter.clamped
        stamp = self.get_clock().now().to_msg()
        if self.excitation.active:
            added = self.excitation.next()
            u += added
            excitation = Excitation(step=msg.step, tension=self.scale.u_to_tension(added))
            excitation.header.stamp = stamp
            self.excitation_pub.publish(excitation)
        u = self.limiter(u)
        if hasattr(self.controller, 'applied'):   # the observer must know what was sent
            self.controller.applied(u)
        tension = self.scale.u_to_tension(u)
        command = tension_msg(tension, msg.step, stamp)
        self.pub.publish(command)
        self.last_answer = (key, command)
        self.counts['commands'] += 1
        status = (ControllerStatus.SOLVER_FALLBACK if self.controller.fallbacks > fallbacks
                  else ControllerStatus.CLAMPED if self.limiter.clamped > clamped
                  else ControllerStatus.OK)
        self.publish_status(msg.step, status, elapsed, tension)

    def configuration(self, settings):
        """What the bag records about this controller (RunInfo): law, settings, model and its
        weights' hash, units scale, clamp, excitation."""
        model = getattr(self.controller, 'model', None)
        config = {'controller': self.law_name,
                  'settings': {k: list(v) if isinstance(v, tuple) else v
                               for k, v in dataclasses.asdict(settings).items()},
                  'scale': scale_dict(self.scale),
                  'max_tension': self.scale.u_to_tension(self.limiter.u_max),
                  'observer': dict(dataclasses.asdict(self.observer_settings)),
                  'excitation': dict(dataclasses.asdict(self.excitation.settings))}
        if model is not None and model.path:
            with open(os.path.join(model.path, WEIGHTS_FILE), 'rb') as weights:
                digest = hashlib.sha256(weights.read()).hexdigest()
            config['model'] = {'path': os.path.abspath(model.path), 'weights_sha256': digest}
        return config

    def publish_status(self, step, status, compute_time=math.nan, tension=math.nan):
        msg = ControllerStatus(step=int(step), status=int(status), controller=self.law_name,
                               compute_time=float(compute_time), tension=float(tension),
                               commands=int(self.counts['commands']),
                               clamped=int(self.limiter.clamped),
                               solver_fallbacks=int(self.controller.fallbacks),
                               non_finite_states=int(self.counts['non_finite_states']),
                               state_timeouts=int(self.counts['state_timeouts']))
        msg.header.stamp = self.get_clock().now().to_msg()
        self.status_pub.publish(msg)

    def check_state_timeout(self):
        if time.monotonic() - self.last_state_wall < self.state_timeout:
            return
        self.counts['state_timeouts'] += 1
        self.get_logger().warning(f'no state for {self.state_timeout:g} s: publishing the safe '
                                  f'tension {self.safe_tension:.4g} N', throttle_duration_sec=5.0)
        self.pub.publish(tension_msg(self.safe_tension, NO_STEP,
                                     self.get_clock().now().to_msg()))
        self.publish_status(NO_STEP, ControllerStatus.SAFE_TENSION,
                            tension=self.safe_tension)

    def report(self):
        """A closing line for people reading the log (tools read the bag, not this)."""
        if self.compute_seconds:
            times = np.array(self.compute_seconds) * 1e6
            print(f'[tsr_controller] {self.counts["commands"]} commands, compute median '
                  f'{np.median(times):.1f} us, p99 {np.percentile(times, 99):.1f} us, '
                  f'clamped {self.limiter.clamped}, solver fallbacks '
                  f'{self.controller.fallbacks}, non-finite states '
                  f'{self.counts["non_finite_states"]}, state timeouts '
                  f'{self.counts["state_timeouts"]}, repeated states resent '
                  f'{self.counts["resent"]}', flush=True)


def main(args=None):
    return run_node(ControllerNode, on_exit=ControllerNode.report, args=args)


if __name__ == '__main__':
    sys.exit(main())
