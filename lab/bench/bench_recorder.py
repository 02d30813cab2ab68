"""Recorder throughput with zero loss against a bare rclpy subscriber, and what a kill -9 loses.

1. A burst of N messages (default 100 000) from this process goes to (a) the recorder node and
   (b) a bare raw subscriber on the same executor that only counts, each in its own process.
   Rate: N over the time from the first publish until every message is acknowledged; the
   recorder is then stopped at once (SIGINT) and its bag must hold exactly N, in order.
2. A steady stream (default 2 000 msg/s) to the recorder, killed with SIGKILL at a random
   moment: the messages published before the kill that are missing from the bag, in seconds of
   the stream (the recorder's flush_period, 1 s, is the bound).
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
from tsr_koopman_ctrl.launcher import NodeProcess, reserve_domain

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402

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
    return elapsed


def start_recorder(domain, tmp, name, topic=TOPIC, env=None):
    return NodeProcess('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                       {'topics': [topic], 'output_dir': tmp, 'bag_name': name,
                        'discovery_period': 0.05},
                       domain_id=domain, log_path=os.path.join(tmp, f'{name}.log'), env=env)


#: The killed recorders talk UDP only. Over Fast DDS's shared-memory transport a participant
#: started right after another was killed -9 on this host is matched but often gets no data
#: (eProsima/Fast-DDS#5053, #2811; here 2 of 6 restarts recorded nothing in 3-5 s, 0 of 6 over
#: UDP): a transport fault, not the recorder's, and docs/reliability.md says so.
KILLED_RECORDER_ENV = {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'}


def kill_loss(node, domain, tmp, rate, seconds, name):
    """Seconds of a `rate` msg/s stream lost by a SIGKILL after `seconds` (each run its own
    bag `name`: the recorder never overwrites a bag, so a reused name would read an old one).
    Each run has its own topic too: a killed recorder's subscription stays in the graph until
    its DDS lease expires, so on a shared topic the next run would start publishing before
    the new recorder has matched."""
    topic = f'{TOPIC}_{name}'
    recorder = start_recorder(domain, tmp, name, topic, KILLED_RECORDER_ENV)
    pub = node.create_publisher(UInt64, topic, BURST_QOS)
    while pub.get_subscription_count() == 0:
        time.sleep(0.05)
    start, sent = time.perf_counter(), 0
    while time.perf_counter() - start < seconds:
        due = int((time.perf_counter() - start) * rate)
        while sent < due:
            pub.publish(UInt64(data=sent))
            sent += 1
        time.sleep(0.001)
    recorder.kill()
    node.destroy_publisher(pub)
    kept = [m.data for _, m in BagReader(os.path.join(tmp, name)).decoded()]
    return (sent - len(kept)) / rate, sent, len(kept), kept == list(range(len(kept)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--messages', type=int, default=100_000)
    parser.add_argument('--kill-rate', type=int, default=2000, help='msg/s of the killed stream')
    parser.add_argument('--kills', type=int, default=3)
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    n = args.messages
    reservation = reserve_domain()      # one no other process on the host uses, held to the end
    domain = reservation.id
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node('bench_publisher', context=context)
    with tempfile.TemporaryDirectory() as tmp:
        recorder = start_recorder(domain, tmp, 'bench')
        rec_s = burst(node, n)
        stopped = recorder.stop()        # at once: the drain must take what was acknowledged
        got = [m.data for _, m in BagReader(os.path.join(tmp, 'bench')).decoded()]

        count_file = os.path.join(tmp, 'count')
        bare = subprocess.Popen([sys.executable, os.path.join(os.path.dirname(__file__),
                                                              'bare_subscriber.py'), count_file],
                                env=dict(os.environ, ROS_DOMAIN_ID=str(domain)))
        bare_s = burst(node, n)
        time.sleep(1.0)   # acked means queued at the subscriber: let it count
        bare.send_signal(2)
        bare.wait(10)
        bare_count = int(open(count_file).read())
        kills = [kill_loss(node, domain, tmp, args.kill_rate, random.uniform(3.0, 6.0),
                           f'killed_{index}') for index in range(args.kills)]
    node.destroy_node()
    rclpy.shutdown(context=context)
    reservation.release()
    say(f'recorder: {n} messages in {rec_s:.2f} s = {n / rec_s:,.0f} msg/s; stopped at once '
        f'(exit {stopped}): in bag {len(got)} (lost {n - len(got)}, in order: '
        f'{got == list(range(len(got)))})')
    say(f'bare rclpy subscriber (EventsExecutor): {n / bare_s:,.0f} msg/s '
        f'(received {bare_count})')
    say(f'ratio recorder / bare subscriber: {bare_s / rec_s:.2f}')
    for lost_s, sent, kept, ordered in kills:
        say(f'kill -9 during a {args.kill_rate} msg/s stream: {sent} sent, {kept} in the bag, '
            f'lost {lost_s:.2f} s of stream (in order: {ordered})')
    say.publish()


if __name__ == '__main__':
    main()
