"""Comparison for bench_recorder: a bare rclpy raw subscriber that only counts messages, on the
executor the project's nodes use (EventsExecutor).

Started as its own process; writes the count to the file named by argv[1] when stopped.
"""

import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt64


def main():
    rclpy.init()
    node = rclpy.create_node('bare_subscriber')
    count = [0]
    node.create_subscription(UInt64, '/bench/counter', lambda _: count.__setitem__(
        0, count[0] + 1), QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1,
                                     reliability=ReliabilityPolicy.RELIABLE), raw=True)
    executor = EventsExecutor()
    executor.add_node(node)
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        with open(sys.argv[1], 'w') as f:
            f.write(str(count[0]))
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
