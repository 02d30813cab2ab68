"""The fault suite: nodes killed, stopped mid-burst and fed bad input, with every count
compared to what was sent. Run alone with `scripts/test.sh -m fault`."""

import math
import random
import signal
import time

import numpy as np
import pytest
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from tsr_sim import wire

from tsr_koopman_ctrl.bag import BagReader, read_loop

pytestmark = [pytest.mark.ros, pytest.mark.fault]

KEEP_ALL = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1,
                      reliability=ReliabilityPolicy.RELIABLE)


def publish_all(ros, pub, messages):
    """Publish every message as fast as DDS takes them: a keep-all writer whose history is full
    refuses a sample after its blocking time (RCLError), so wait a moment and offer it again."""
    from rclpy._rclpy_pybind11 import RCLError
    for msg in messages:
        while True:
            try:
                pub.publish(msg)
                break
            except RCLError:
                ros.spin_for(0.01)
    assert pub.wait_for_all_acked(Duration(seconds=60))


def test_sigint_right_after_a_burst_keeps_every_acknowledged_message(ros, start_node, tmp_path):
    from std_msgs.msg import UInt64
    n = 20_000
    recorder = start_node('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                          {'topics': ['/fault/counter'], 'output_dir': str(tmp_path),
                           'bag_name': 'burst', 'discovery_period': 0.05})
    pub = ros.node.create_publisher(UInt64, '/fault/counter', KEEP_ALL)
    ros.spin_until(lambda: pub.get_subscription_count() > 0, timeout=20,
                   what='the recorder to subscribe')
    publish_all(ros, pub, (UInt64(data=i) for i in range(n)))
    assert recorder.stop(signal.SIGINT) == 0      # at once: no time to catch up first
    reader = BagReader(str(tmp_path / 'burst'))
    assert [msg.data for _, msg in reader.decoded()] == list(range(n))
    assert not reader.report.recovered


def start_loop(start_node, tmp_path, name, steps=100_000, flush_period=1.0, watchers=0,
               namespace=None):
    """A lockstep loop (linear_lqr: the transport, not the law, sets the pace) and a recorder.
    `watchers`: the test's own subscriptions to the state, which the simulator must not count
    as the recorder (it waits for controller, recorder and those before its first step).
    `namespace`: a loop of its own, so that a recorder killed by an earlier run, whose
    subscription stays in the graph until its DDS lease expires, is not counted either."""
    recorder = start_node('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                          {'output_dir': str(tmp_path), 'bag_name': name,
                           'flush_period': flush_period}, namespace=namespace)
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller',
               {'law': 'linear_lqr', 'wait_for_subscribers': 2}, namespace=namespace)
    start_node('tsr_sim', 'sim_node', 'tsr_sim',
               {'max_steps': steps, 'progress_every': 0,
                'wait_for_subscribers': 2 + watchers}, namespace=namespace)
    return recorder


@pytest.mark.parametrize('run', range(3))
def test_kill_9_of_the_recorder_loses_at_most_the_flush_period(ros, start_node, tmp_path, run):
    """Watch the states on the wire, kill -9 the recorder at a random moment, and check that
    the bag holds every state seen more than flush_period (1 s) before the kill."""
    from tsr_msgs.msg import TsrState
    from tsr_sim import ros_io
    seen = []      # (wall time, step)
    namespace = f'/kill{run}'
    ros.node.create_subscription(TsrState, wire.resolve(wire.STATE_TOPIC, namespace),
                                 lambda m: seen.append((time.monotonic(), m.step)),
                                 ros_io.LOOP_QOS)
    recorder = start_loop(start_node, tmp_path, f'kill{run}', watchers=1, namespace=namespace)
    ros.spin_until(lambda: len(seen) > 200, timeout=30, what='the loop to run')
    ros.spin_for(random.Random(run).uniform(1.5, 4.0))
    killed_at = time.monotonic()
    recorder.kill()
    margin = 1.0 + 0.2          # flush_period, and the timer's own period
    due = max((step for wall, step in seen if wall <= killed_at - margin), default=-1)
    loop = read_loop(str(tmp_path / f'kill{run}'))
    assert loop.report.recovered
    assert loop.step[-1] >= due, f'lost steps {loop.step[-1] + 1}..{due}'
    assert loop.step.tolist() == list(range(len(loop.step)))   # no hole before the loss


def test_controller_killed_and_restarted_in_lockstep(ros, start_node, tmp_path):
    from tsr_msgs.msg import SimStatus
    from tsr_sim import ros_io
    status = []
    ros.node.create_subscription(SimStatus, wire.SIM_STATUS_TOPIC, status.append,
                                 ros_io.LATCHED_QOS)
    sim = start_node('tsr_sim', 'sim_node', 'tsr_sim',
                     {'progress_every': 0, 'republish_period': 0.2})
    params = {'law': 'linear_lqr'}
    first = start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller', params)
    ros.spin_until(lambda: status and status[-1].step > 300, timeout=30, what='300 steps')
    first.kill()
    ros.spin_for(1.0)
    stalled = status[-1].step
    ros.spin_for(1.0)
    assert status[-1].step == stalled     # lockstep waits for its controller
    # Said at once (the simulator warns after 0.5 s; before the fix, after 10 s): within 5 s of
    # the kill, the slack for a loaded machine's timers and log writes.
    said = f'no tension command for step {stalled}'
    deadline = time.monotonic() + 3.0
    while said not in (tmp_path / 'tsr_sim.log').read_text() and time.monotonic() < deadline:
        ros.spin_for(0.1)
    assert said in (tmp_path / 'tsr_sim.log').read_text()
    start_node('tsr_koopman_ctrl', 'controller_node', 'tsr_controller', params)
    ros.spin_until(lambda: status[-1].step > stalled + 300, timeout=30,
                   what='the restarted controller to resume the loop')
    last = status[-1]
    assert last.rejected_non_finite + last.rejected_negative + last.rejected_over_limit == 0
    assert sim.running()


def test_a_burst_of_bad_commands_is_counted_in_full(ros, start_node):
    from tsr_msgs.msg import SimStatus, TensionCommand
    from tsr_sim import ros_io
    n = 10_000
    status = []
    start_node('tsr_sim', 'sim_node', 'tsr_sim', {'progress_every': 0})
    ros.node.create_subscription(SimStatus, wire.SIM_STATUS_TOPIC, status.append,
                                 ros_io.LATCHED_QOS)
    pub = ros.node.create_publisher(TensionCommand, wire.TENSION_TOPIC, KEEP_ALL)
    ros.spin_until(lambda: pub.get_subscription_count() > 0 and status, timeout=20,
                   what='the simulator')
    stamp = ros.node.get_clock().now().to_msg()
    bad = [math.nan, -1.0, 1e6, math.inf]
    publish_all(ros, pub, (wire.tension_msg(bad[i % 4], 0, stamp) for i in range(n)))
    ros.spin_until(lambda: sum(counts(status[-1])) == n, timeout=30,
                   what=f'{n} rejections counted')
    non_finite, negative, over = counts(status[-1])
    assert (non_finite, negative, over) == (n // 2, n // 4, n // 4)
    assert status[-1].commands_accepted == 0 and status[-1].step == 0


def counts(status):
    return (status.rejected_non_finite, status.rejected_negative, status.rejected_over_limit)


def test_recorder_bag_of_a_killed_deployment_recovers_with_the_command(start_node, tmp_path,
                                                                       ros):
    """kill -9 mid-deployment, then `bag recover`: a complete bag that rosbags opens."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import get_typestore, Stores

    from tsr_koopman_ctrl.commands import bag as bag_tool
    from tsr_msgs.msg import TsrState
    from tsr_sim import ros_io
    seen = []
    ros.node.create_subscription(TsrState, wire.STATE_TOPIC, seen.append, ros_io.LOOP_QOS)
    recorder = start_loop(start_node, tmp_path, 'killed', watchers=1)
    ros.spin_until(lambda: len(seen) > 200, timeout=30, what='the loop to run')
    ros.spin_for(2.0)
    recorder.kill()
    killed = str(tmp_path / 'killed')
    kept = read_loop(killed)
    assert bag_tool.main(['recover', killed, '--out', str(tmp_path / 'fixed')]) == 0
    fixed = read_loop(str(tmp_path / 'fixed'))
    assert not fixed.report.recovered
    np.testing.assert_array_equal(fixed.step, kept.step)
    np.testing.assert_array_equal(fixed.x, kept.x)
    with AnyReader([tmp_path / 'fixed'],
                   default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        states = sum(c.msgcount for c in reader.connections
                     if c.topic == wire.resolve(wire.STATE_TOPIC, ros.namespace))
    assert states >= kept.step.size
