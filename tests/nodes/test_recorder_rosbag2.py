"""The recorder node stores what `ros2 bag record` (rosbag2 0.26, Jazzy) stores: the schema
text rosbag2 spells, the publisher's type hash, sequence 0, the log time when the message was
received and the publish time when it was sent (rclpy's MessageInfo, taken with raw=True on the
EventsExecutor the nodes spin; rosbag2_storage_mcap/src/mcap_storage.cpp and
rosbag2_transport/src/rosbag2_transport/recorder.cpp at tag 0.26.5)."""

import signal
import sys
import time

from builtin_interfaces.msg import Time
from mcap.reader import make_reader
import numpy as np
import pytest
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from tsr_sim import wire

from conftest import ROOT

from tsr_koopman_ctrl.bag import definitions

sys.path.insert(0, str(ROOT / 'tests' / 'bag'))
import rosbag2_style  # noqa: E402

pytestmark = pytest.mark.ros

TOPIC = '/test/state'
TYPE = 'tsr_msgs/msg/TsrState'


def test_the_recorder_stores_schema_hash_and_times_as_rosbag2(ros, start_node, tmp_path):
    from tsr_msgs.msg import TsrState
    recorder = start_node('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                          {'topics': [TOPIC], 'types': [TYPE], 'output_dir': str(tmp_path),
                           'bag_name': 'rec', 'discovery_period': 0.05})
    pub = ros.node.create_publisher(TsrState, TOPIC, QoSProfile(
        history=HistoryPolicy.KEEP_ALL, depth=1, reliability=ReliabilityPolicy.RELIABLE))
    ros.spin_until(lambda: pub.get_subscription_count() > 0, timeout=20,
                   what='the recorder to subscribe')
    before = time.time_ns()
    for step in range(20):
        pub.publish(wire.state_to_msg(np.array([0.1, 0.0, 1000.0, 1.0]), step, Time()))
    assert pub.wait_for_all_acked(Duration(seconds=30))
    ros.spin_for(1.0)
    assert recorder.stop(signal.SIGINT) == 0
    with open(tmp_path / 'rec' / 'rec_0.mcap', 'rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        messages = [m for _, _, m in reader.iter_messages()]
    (schema,) = summary.schemas.values()
    (channel,) = summary.channels.values()
    assert schema.data.decode() == rosbag2_style.full_text(TYPE)
    assert channel.metadata['topic_type_hash'] == definitions.type_hash(TYPE) != ''
    assert len(messages) == 20 and {m.sequence for m in messages} == {0}
    # Sent by this process (its source timestamp), then received by the recorder's reader.
    assert all(before <= m.publish_time < m.log_time < time.time_ns() for m in messages)
