"""Recorder throughput with zero loss, against a bare rclpy subscriber, in one run.

A burst of N messages from this process goes to (a) the recorder node and (b) a bare raw
subscriber that only counts, each in its own process. Rate: N over the time from the first
publish until every message is acknowledged. The bag must hold exactly N, in order.
"""

import argparse
import os
import random
import subprocess
import sys
import tempfile
import time

import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import UInt64

from tsr_koopman_ctrl.bag import BagReader
from tsr_koopman_ctrl.tools.launcher import NodeProcess

TOPIC = '/bench/counter'
# Deep reliable history: a KEEP_ALL writer errors out once its queue is full on a burst.
BURST_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100_000,
                       reliability=ReliabilityPolicy.RELIABLE)


def burst(node, n):
    pub = node.create_publisher(UInt64, TOPIC, BURST_QOS)
    while pub.get_subscription_count() == 0:
        time.sleep(0.05)
    start = time.perf_counter()
    for i in range(n):
        pub.publish(UInt64(data=i))
    if not pub.wait_for_all_acked(Duration(seconds=120)):
        raise SystemExit('not all messages were acknowledged')
    elapsed = time.perf_counter() - start
    node.destroy_publisher(pub)
    time.sleep(1.0)   # acked means queued at the subscriber: let its callbacks run
    return elapsed


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--messages', type=int, default=20_000)
    args = parser.parse_args()
    n = args.messages
    domain = random.randint(120, 219)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node('bench_publisher', context=context)
    with tempfile.TemporaryDirectory() as tmp:
        recorder = NodeProcess('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                               {'topics': [TOPIC], 'output_dir': tmp, 'bag_name': 'bench',
                                'discovery_period': 0.05},
                               domain_id=domain, log_path=os.path.join(tmp, 'rec.log'))
        rec_s = burst(node, n)
        recorder.stop()
        got = [m.data for _, m in BagReader(os.path.join(tmp, 'bench')).decoded()]

        count_file = os.path.join(tmp, 'count')
        bare = subprocess.Popen([sys.executable, os.path.join(os.path.dirname(__file__),
                                                              'bare_subscriber.py'), count_file],
                                env=dict(os.environ, ROS_DOMAIN_ID=str(domain)))
        bare_s = burst(node, n)
        bare.send_signal(2)
        bare.wait(10)
        bare_count = int(open(count_file).read())
    node.destroy_node()
    rclpy.shutdown(context=context)
    print(f'recorder: {n} messages in {rec_s:.2f} s = {n / rec_s:,.0f} msg/s; in bag '
          f'{len(got)} (lost {n - len(got)}, in order: {got == list(range(len(got)))})')
    print(f'bare rclpy subscriber: {n / bare_s:,.0f} msg/s (received {bare_count})')
    print(f'ratio recorder / bare subscriber: {bare_s / rec_s:.2f}')


if __name__ == '__main__':
    main()
