"""Controller node: answers every TSR state with a tension command for the same step.

SI state in, SI tension out; the control law (tsr_koopman_ctrl.controllers) works in the
paper's dimensionless variables, converted through tsr_sim.units. A non-finite state gets no
command (and a warning); every command is clamped to [0, max_tension] and the clamps counted.
"""

from collections import deque
import math
import sys
import time

import numpy as np
from rclpy.node import Node
from tsr_msgs.msg import TensionCommand, TsrState
from tsr_sim.ros_io import (declare, declare_scale, LOOP_QOS, msg_to_state, run_node,
                            STATE_TOPIC, TENSION_TOPIC, tension_msg)

from tsr_koopman_ctrl.controllers import CONTROLLERS, make_controller, TensionLimiter


class ControllerNode(Node):

    def __init__(self):
        super().__init__('tsr_controller')
        name = declare(self, 'controller', 'linear_lqr',
                       f'control law: one of {sorted(CONTROLLERS)}')
        self.controller = make_controller(name)
        self.scale = declare_scale(self)
        max_tension = declare(self, 'max_tension', self.scale.u_to_tension(5.0),
                              'output clamp [N] (default u = 5)', 1e-9, 1e9)
        self.limiter = TensionLimiter(self.scale.tension_to_u(max_tension))
        self.wait_for_subscribers = declare(
            self, 'wait_for_subscribers', 0, 'send no command until the tension topic has this '
            'many subscribers (simulator, recorder)', 0, 1000)
        self.rejected_states = 0
        self.compute_seconds = deque(maxlen=100_000)
        self.pub = self.create_publisher(TensionCommand, TENSION_TOPIC, LOOP_QOS)
        self.create_subscription(TsrState, STATE_TOPIC, self.on_state, LOOP_QOS)
        self.get_logger().info(f'{name} controller, clamp [0, {max_tension:.4g}] N')

    def on_state(self, msg):
        if self.pub.get_subscription_count() < self.wait_for_subscribers:
            self.get_logger().info(f'waiting for {self.wait_for_subscribers} subscribers to '
                                   f'{TENSION_TOPIC}', throttle_duration_sec=5.0)
            return
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

    def report(self):
        if self.compute_seconds:
            times = np.array(self.compute_seconds) * 1e6
            print(f'[tsr_controller] {times.size} commands, compute median '
                  f'{np.median(times):.1f} us, p99 {np.percentile(times, 99):.1f} us, '
                  f'clamped {self.limiter.clamped}, non-finite states {self.rejected_states}',
                  flush=True)


def main(args=None):
    return run_node(ControllerNode, on_exit=ControllerNode.report, args=args)


if __name__ == '__main__':
    sys.exit(main())
