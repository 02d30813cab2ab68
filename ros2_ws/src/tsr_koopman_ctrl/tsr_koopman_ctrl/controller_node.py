"""Controller node: answers every TSR state with a tension command for the same step.

SI state in, SI tension out; the control law (tsr_koopman_ctrl.controllers) works in the
paper's dimensionless variables, converted through tsr_sim.units. A non-finite state gets no
command (and a warning); every command is clamped to [0, max_tension] and the clamps counted.
With no state for `state_timeout` wall seconds the node publishes `safe_tension` (default: the
equilibrium tension, u = 3) every `state_timeout` seconds with a warning, until states return.
A missing or bad model (koopman_* laws) stops the node at start with one line (exit 2).
"""

from collections import deque
import math
import sys
import time

import numpy as np
from rclpy.node import Node
from tsr_msgs.msg import TensionCommand, TsrState
from tsr_sim import dynamics
from tsr_sim.ros_io import (declare, declare_scale, LOOP_PUBLISHER_QOS, LOOP_QOS, msg_to_state,
                            run_node, STATE_TOPIC, TENSION_TOPIC, tension_msg)

from tsr_koopman_ctrl.controllers import (CONTROLLERS, DEFAULT_MODEL, make_controller,
                                          TensionLimiter)


class ControllerNode(Node):

    def __init__(self):
        super().__init__('tsr_controller')
        name = declare(self, 'controller', 'koopman_mpc',
                       f'control law: one of {sorted(CONTROLLERS)}')
        model = declare(self, 'model', DEFAULT_MODEL, 'koopman_* laws: model directory '
                        '(relative to the working directory or absolute)')
        r = declare(self, 'lqr_r', 15.0, "koopman_lqr: R' (paper: 15)", 1e-9, 1e9)
        state_weight = declare(self, 'lqr_state_weight', 'lifted',
                               "koopman_lqr: Q' = I ('lifted', paper) or C^T C ('state')")
        horizon = declare(self, 'mpc_horizon', 5, 'koopman_mpc: prediction steps', 1, 200)
        theta_max = declare(self, 'mpc_theta_max', 0.8, 'koopman_mpc: soft bound on |theta| '
                            '[rad]', 0.01, 3.2)
        overshoot_max = declare(self, 'mpc_overshoot_max', 0.05, 'koopman_mpc: soft bound on '
                                'l - 1 (fraction of the tether length)', 0.0, 10.0)
        options = {'koopman_lqr': {'model': model, 'r': r, 'state_weight': state_weight},
                   'koopman_mpc': {'model': model, 'horizon': horizon, 'theta_max': theta_max,
                                   'overshoot_max': overshoot_max}}.get(name, {})
        self.controller = make_controller(name, **options)
        self.scale = declare_scale(self)
        max_tension = declare(self, 'max_tension', self.scale.u_to_tension(5.0),
                              'output clamp [N] (default u = 5)', 1e-9, 1e9)
        self.safe_tension = declare(
            self, 'safe_tension', self.scale.u_to_tension(dynamics.EQUILIBRIUM_TENSION),
            'published when no state arrives for state_timeout [N] (default: u = 3, which '
            'holds the deployed equilibrium)', 0.0, max_tension)
        self.state_timeout = declare(self, 'state_timeout', 5.0, 'wall seconds without a state '
                                     'before safe_tension is published', 0.01, 3600.0)
        self.limiter = TensionLimiter(self.scale.tension_to_u(max_tension))
        self.wait_for_subscribers = declare(
            self, 'wait_for_subscribers', 0, 'send no command until the tension topic has this '
            'many subscribers (simulator, recorder)', 0, 1000)
        self.rejected_states = 0
        self.state_timeouts = 0
        self.last_state_wall = time.monotonic()
        self.last_step = 0
        self.compute_seconds = deque(maxlen=100_000)
        self.pub = self.create_publisher(TensionCommand, TENSION_TOPIC, LOOP_PUBLISHER_QOS)
        self.create_subscription(TsrState, STATE_TOPIC, self.on_state, LOOP_QOS)
        self.create_timer(self.state_timeout, self.check_state_timeout)
        self.get_logger().info(f'{name} controller, clamp [0, {max_tension:.4g}] N')

    def on_state(self, msg):
        if self.pub.get_subscription_count() < self.wait_for_subscribers:
            self.get_logger().info(f'waiting for {self.wait_for_subscribers} subscribers to '
                                   f'{TENSION_TOPIC}', throttle_duration_sec=5.0)
            return
        self.last_state_wall, self.last_step = time.monotonic(), msg.step
        si = msg_to_state(msg)
        if not np.all(np.isfinite(si)):
            self.rejected_states += 1
            self.get_logger().warning(f'non-finite state at step {msg.step}: no command',
                                      throttle_duration_sec=1.0)
            return
        start = time.perf_counter()
        u = self.controller.compute(self.scale.state_from_si(si))
        self.compute_seconds.append(time.perf_counter() - start)
        if not math.isfinite(u):
            self.get_logger().error(f'controller gave u = {u} at step {msg.step}: no command',
                                    throttle_duration_sec=1.0)
            return
        tension = self.scale.u_to_tension(self.limiter(u))
        self.pub.publish(tension_msg(tension, msg.step, self.get_clock().now().to_msg()))

    def check_state_timeout(self):
        if time.monotonic() - self.last_state_wall < self.state_timeout:
            return
        self.state_timeouts += 1
        self.get_logger().warning(f'no state for {self.state_timeout:g} s: publishing the safe '
                                  f'tension {self.safe_tension:.4g} N', throttle_duration_sec=5.0)
        self.pub.publish(tension_msg(self.safe_tension, self.last_step,
                                     self.get_clock().now().to_msg()))

    def report(self):
        if self.compute_seconds:
            times = np.array(self.compute_seconds) * 1e6
            print(f'[tsr_controller] {times.size} commands, compute median '
                  f'{np.median(times):.1f} us, p99 {np.percentile(times, 99):.1f} us, '
                  f'clamped {self.limiter.clamped}, non-finite states {self.rejected_states}, '
                  f'state timeouts {self.state_timeouts}',
                  flush=True)


def main(args=None):
    return run_node(ControllerNode, on_exit=ControllerNode.report, args=args)


if __name__ == '__main__':
    sys.exit(main())
