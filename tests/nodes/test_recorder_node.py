"""The recorder node as a separate process: nothing lost, clean close on signals, crash recovery.

Bags are read twice: with the project's reader and with the independent rosbags library.
"""

import signal

from mcap.reader import make_reader
import pytest
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
from std_msgs.msg import UInt64
import yaml

from tsr_koopman_ctrl.bag import BagReader

pytestmark = pytest.mark.ros


TOPIC = '/test/counter'
BURST_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1,
                       reliability=ReliabilityPolicy.RELIABLE)


def start_recorder(start_node, tmp_path, **params):
    return start_node('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                      dict({'topics': [TOPIC], 'output_dir': str(tmp_path), 'bag_name': 'rec',
                            'discovery_period': 0.05}, **params))


def publish_burst(ros, n, hold=0.0, after=1.0):
    """Publish 0..n-1 as fast as rclpy goes, `hold` seconds after the recorder subscribed;
    return `after` seconds after the last was acknowledged."""
    pub = ros.node.create_publisher(UInt64, TOPIC, BURST_QOS)
    ros.spin_until(lambda: pub.get_subscription_count() > 0, timeout=20,
                   what='the recorder to subscribe')
    ros.spin_for(hold)
    for i in range(n):
        pub.publish(UInt64(data=i))
    assert pub.wait_for_all_acked(Duration(seconds=30))
    ros.spin_for(after)  # acked means in the recorder's queue: let its callbacks run


def counters_in_bag(path):
    return [msg.data for _, msg in BagReader(str(path)).decoded()]


def counters_with_rosbags(path):
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        return [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages()]


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_burst_recorded_exactly_and_in_order(ros, start_node, tmp_path, sig):
    n = 5000
    recorder = start_recorder(start_node, tmp_path, max_file_size=64_000, chunk_size=16_000)
    publish_burst(ros, n)
    assert recorder.stop(sig) == 0
    expected = list(range(n))
    assert counters_in_bag(tmp_path / 'rec') == expected
    assert counters_with_rosbags(tmp_path / 'rec') == expected
    assert len(list((tmp_path / 'rec').glob('*.mcap'))) > 1    # it did split


def test_sigkill_leaves_a_recoverable_bag(ros, start_node, tmp_path):
    """Without the time bound (flush_period 0) a kill loses the chunk in progress."""
    n = 4000
    recorder = start_recorder(start_node, tmp_path, chunk_size=4_000, flush_period=0.0)
    publish_burst(ros, n)
    recorder.kill()
    reader = BagReader(str(tmp_path / 'rec'))
    got = [msg.data for _, msg in reader.decoded()]
    assert reader.report.recovered, reader.report.summary()
    # Everything but the last, unfinished chunk (a few hundred tiny messages) survives, in order.
    assert n - 500 <= len(got) < n
    assert got == list(range(len(got)))


def test_sigkill_after_the_flush_period_loses_nothing(ros, start_node, tmp_path):
    n = 4000
    recorder = start_recorder(start_node, tmp_path, flush_period=0.5)
    # 2 s after the last acknowledgement: the flush period, its 0.2-s timer and slack for a
    # loaded machine to take 4000 messages first.
    publish_burst(ros, n, after=2.0)
    recorder.kill()
    reader = BagReader(str(tmp_path / 'rec'))
    assert [msg.data for _, msg in reader.decoded()] == list(range(n))
    assert reader.report.recovered     # killed: no summary, but every chunk was written


def test_a_matched_topic_that_stays_silent_is_logged_once(ros, start_node, tmp_path):
    """The recorder cannot tell a silent publisher from a transport that delivers nothing (Fast
    DDS shared memory after a kill -9): either way it says so, once, naming the topic. Its clock
    starts when a publisher matches: one that appears late and sends within the time is fine."""
    silent = '/test/silent'
    start_recorder(start_node, tmp_path, topics=[TOPIC, silent],
                   types=['std_msgs/msg/UInt64'] * 2, silence_warning=2.0)
    log = tmp_path / 'tsr_recorder.log'
    quiet = ros.node.create_publisher(UInt64, silent, BURST_QOS)
    ros.spin_until(lambda: quiet.get_subscription_count() > 0, timeout=20,
                   what='the recorder to subscribe')
    ros.spin_for(2.5)              # both subscriptions are now older than the warning time
    # Matched 1.2 s before its first message: over one 1-s check, under the 2-s warning.
    publish_burst(ros, 10, hold=1.2)
    warning = f'no message on {silent} for 2 s although 1 publisher(s)'
    ros.spin_until(lambda: warning in log.read_text(), timeout=20, what='the silence warning')
    ros.spin_for(2.5)              # two more checks: it is not repeated
    assert log.read_text().count(warning) == 1, log.read_text()
    assert f'no message on {TOPIC}' not in log.read_text()


@pytest.mark.parametrize('discovery_period', [0.05, 60.0])
def test_the_publishers_offered_qos_is_in_the_bag_of_topics_subscribed_at_start(
        ros, start_node, tmp_path, discovery_period):
    """Topics and types given: subscribed before any publisher exists, yet the bag carries the
    publishers' QoS, as `ros2 bag record` writes it (metadata.yaml and the MCAP channel). It is
    learnt by the discovery timer, or (a 60-s period: never before the first message) at the
    first message, which is recorded all the same, or at the close for a silent topic."""
    silent = '/test/silent'
    recorder = start_recorder(start_node, tmp_path, topics=[TOPIC, silent],
                              types=['std_msgs/msg/UInt64'] * 2,
                              discovery_period=discovery_period)
    quiet = ros.node.create_publisher(UInt64, silent, QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE))
    ros.spin_until(lambda: quiet.get_subscription_count() > 0, timeout=20,
                   what='the recorder to subscribe')
    pub = ros.node.create_publisher(UInt64, TOPIC, QoSProfile(
        depth=100, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    ros.spin_until(lambda: pub.get_subscription_count() > 0, timeout=20,
                   what='the recorder to subscribe')
    ros.spin_for(0.5)              # several discovery periods, or none
    for i in range(50):
        pub.publish(UInt64(data=i))
    assert pub.wait_for_all_acked(Duration(seconds=30))
    ros.spin_for(1.0)
    assert recorder.stop(signal.SIGINT) == 0
    bag_dir = tmp_path / 'rec'
    assert counters_with_rosbags(bag_dir) == list(range(50))
    # As metadata version 9 names them (rosbags' own writer names them so too).
    expected = {TOPIC: [('reliable', 'transient_local')], silent: [('reliable', 'volatile')]}
    with AnyReader([bag_dir], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        from_metadata = {c.topic: [(q.reliability.name.lower(), q.durability.name.lower())
                                   for q in c.ext.offered_qos_profiles]
                         for c in reader.connections}
    assert from_metadata == expected
    with open(bag_dir / 'rec_0.mcap', 'rb') as f:
        channels = make_reader(f).get_summary().channels.values()
    from_channels = {c.topic: [(q['reliability'], q['durability'])
                               for q in yaml.safe_load(c.metadata['offered_qos_profiles'])]
                     for c in channels}
    assert from_channels == expected


@pytest.mark.parametrize('params, message', [
    ({'types': ['counter']}, "cannot start: 'counter' is not a message type (pkg/msg/Type)"),
    ({'types': ['std_msgs/msg/Nope']}, "cannot start: no message type 'std_msgs/msg/Nope'"),
    ({'output_dir': 'FILE'}, 'cannot start: [Errno 20] Not a directory')])
def test_a_bad_message_type_or_output_dir_stops_the_recorder_before_any_bag_exists(
        start_node, tmp_path, params, message):
    bags = tmp_path / 'bags'
    if params.get('output_dir') == 'FILE':
        params = {'output_dir': str(tmp_path / 'notes.txt')}
        (tmp_path / 'notes.txt').write_text('my notes\n')
    recorder = start_recorder(start_node, bags, **params)
    assert recorder.wait(timeout=30) == 2
    log = (tmp_path / 'tsr_recorder.log').read_text()
    assert message in log and 'Traceback' not in log
    assert not bags.exists()
