"""Recorder node: raw CDR subscriptions written as they arrive into a rosbag2-layout MCAP bag.

Topics are subscribed once a publisher shows their type (the loop's own topics at start, their
types being known); the subscription is reliable and keeps all messages (nothing dropped on a
burst), transient local where every publisher is. A topic subscribed at start gets its
publishers' offered QoS in the bag (as `ros2 bag record` writes it) when they are first seen:
by the discovery timer, or at its first message, which is written at once either way. Relative
topic names resolve in the node's namespace, as the loop's publishers' do. SIGINT and SIGTERM
close the bag cleanly; the bag format itself is in `tsr_koopman_ctrl.bag`. Its parameters are
declared from one schema class (`recorder_parameters.RecorderNodeSettings`).
"""

import importlib
import os
import sys
import time

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tsr_sim.ros_io import (declare_schema, Health, Parameters, run_node,
                            spin_until_quiet, steady_timer)
from rosgraph_msgs.msg import Clock
from tsr_sim.wire import CLOCK_TOPIC, LATCHED_TOPICS

from tsr_koopman_ctrl.bag import definitions
from tsr_koopman_ctrl.bag.writer import BagWriter, new_bag_name, ReceivedCallback
from tsr_koopman_ctrl.nodes.recorder_parameters import (DEFAULT_TOPICS, DEFAULT_TYPES,
                                                        RecorderNodeSettings)


def message_class(type_name):
    """'pkg/msg/Type' -> the generated Python class (ValueError if there is none)."""
    parts = type_name.split('/')
    if len(parts) != 3 or parts[1] != 'msg' or not all(parts):
        raise ValueError(f'{type_name!r} is not a message type (pkg/msg/Type)')
    package, kind, name = parts
    try:
        return getattr(importlib.import_module(f'{package}.{kind}'), name)
    except (ImportError, AttributeError):
        raise ValueError(f'no message type {type_name!r} (is its package installed and '
                         'the workspace sourced?)') from None


def offered_qos(endpoint):
    q = endpoint.qos_profile
    return definitions.qos_dict(q.history, q.depth, q.reliability, q.durability,
                                q.liveliness, q.deadline.nanoseconds, q.lifespan.nanoseconds,
                                q.liveliness_lease_duration.nanoseconds,
                                q.avoid_ros_namespace_conventions)


class RecorderNode(Node):

    NODE_NAME = 'tsr_recorder'

    def __init__(self):
        super().__init__(self.NODE_NAME)
        loop = self.resolved(DEFAULT_TOPICS)
        # The loop's types for the loop's topics; other topics' are discovered by default.
        params = declare_schema(self, RecorderNodeSettings, defaults={'types': (
            lambda declared: DEFAULT_TYPES if self.resolved(declared['topics']) == loop
            else [''])})
        self.wanted = self.resolved(params['topics'])
        types = list(params['types'])
        for type_name in filter(None, types):
            message_class(type_name)      # a bad type stops the node before any bag exists
        directory = params['output_dir']
        name = params['bag_name'] or new_bag_name(directory, 'tsr')
        self.writer = BagWriter(
            os.path.join(directory, name), max_file_bytes=params['max_file_size'],
            max_file_seconds=params['max_file_duration'], chunk_size=params['chunk_size'],
            flush_period=params['flush_period'])
        # Checked often and cheaply: a chunk is written once its oldest message is due.
        steady_timer(self, 0.1, self.writer.flush_if_due)
        self.subscribed = {}
        self.matched_since = {}        # topic -> monotonic time its publishers were first seen
        self.silence_warned = set()
        self.silence_warning = params['silence_warning']
        steady_timer(self, 0.5, self.check_silence)
        self.discovery_timer = steady_timer(self, params['discovery_period'], self.discover)
        self.types = types
        self.recording = False
        self.parameters = Parameters(self)
        self.parameters.live('flush_period',
                             lambda v: setattr(self.writer, 'flush_period', float(v)))
        self.parameters.live('max_file_size', lambda v: setattr(self.writer, 'max_file_bytes', v))
        self.parameters.live('max_file_duration',
                             lambda v: setattr(self.writer, 'max_file_ns', int(v * 1e9)))
        self.parameters.live('silence_warning', lambda v: setattr(self, 'silence_warning', v))
        self.parameters.live('discovery_period', self.set_discovery_period)
        self.health = Health(self, 'recorder', self.diagnose)
        self.get_logger().info(f'recording {self.wanted} into {self.writer.directory}')
        self.clock_seen = not self.get_parameter('use_sim_time').value
        if not self.clock_seen:
            self.get_logger().info('use_sim_time: waiting for /clock before recording')
            self.clock_watch = self.create_subscription(Clock, CLOCK_TOPIC, self.on_clock, 1)
        self.start_recording()

    def resolved(self, topics):
        return [self.resolve_topic_name(t) for t in topics]

    def on_clock(self, msg):
        if not self.clock_seen:
            self.clock_seen = True
            self.start_recording()

    def set_discovery_period(self, value):
        self.destroy_timer(self.discovery_timer)
        self.discovery_timer = steady_timer(self, value, self.discover)

    def start_recording(self):
        """Subscribe to the topics whose types are given (so nothing is missed), once the
        clock runs: at once on wall time, at the first /clock on sim time."""
        if self.recording or not self.clock_seen:
            return
        self.recording = True
        latched = {self.resolve_topic_name(t) for t in LATCHED_TOPICS}
        for topic, type_name in zip(self.wanted, self.types):
            if type_name:
                self.subscribe(topic, type_name, publishers=[], latched=topic in latched)
        self.discover()

    def discover(self):
        if not self.recording:
            self.start_recording()
            return
        for topic in list(self.writer.qos_pending):
            self.learn_qos(topic)
        if len(self.subscribed) == len(self.wanted):
            return
        types = dict(self.get_topic_names_and_types())
        for topic in self.wanted:
            if topic in self.subscribed or topic not in types:
                continue
            publishers = self.get_publishers_info_by_topic(topic)
            if not publishers:
                continue
            self.subscribe(topic, types[topic][0], publishers)

    def learn_qos(self, topic):
        """Give a topic subscribed before its publishers were known their offered QoS, once
        they are (else it stays pending: the writer then writes the channel without QoS)."""
        publishers = self.get_publishers_info_by_topic(topic)
        if publishers:
            self.writer.set_offered_qos(topic, [offered_qos(p) for p in publishers])

    def record(self, topic, data, info):
        if topic in self.writer.qos_pending:      # first message before the timer saw them
            self.learn_qos(topic)
        self.writer.write_received(topic, data, info)

    def subscribe(self, topic, type_name, publishers, latched=False):
        """Subscribe raw; with no publisher known yet: reliable, and volatile (matches any)
        unless `latched` (the loop's latched topics, whose publishers are transient local)."""
        qos = [offered_qos(p) for p in publishers]
        self.writer.add_topic(definitions.TopicInfo(
            name=topic, type=type_name, definition=definitions.message_definition(type_name),
            type_hash=definitions.type_hash(type_name), offered_qos=qos),
            qos_pending=not publishers)
        latched = latched or bool(publishers) and all(
            p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
        profile = QoSProfile(
            history=HistoryPolicy.KEEP_ALL, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers):
            profile.reliability = ReliabilityPolicy.BEST_EFFORT
        self.subscribed[topic] = self.create_subscription(
            message_class(type_name), topic,
            ReceivedCallback(lambda data, info, t=topic: self.record(t, data, info)), profile,
            raw=True)
        self.get_logger().info(f'recording {topic} [{type_name}]')

    def silent_topics(self):
        """Topics with matched publishers that have sent nothing for `silence_warning` s."""
        return sorted(t for t in self.silence_warned if not self.writer.topic_counts.get(t))

    def diagnose(self):
        """Health (docs/nodes.md, *Health on /diagnostics*): WARN when a matched topic stays
        silent or, on sim time, no /clock has come yet; OK otherwise. Per topic its message
        count."""
        writer = self.writer
        since_flush = (time.monotonic() - writer.last_flush_wall
                       if writer.last_flush_wall is not None else '')
        values = {'bag': writer.directory, 'messages': writer.message_count,
                  'bytes': writer.bytes_written, 'files': len(writer.files),
                  'seconds_since_flush': since_flush,
                  'silent_topics': ', '.join(self.silent_topics())}
        values.update({f'count {topic}': count for topic, count in writer.topic_counts.items()})
        if not self.recording:
            return Health.WARN, 'use_sim_time: waiting for /clock', values
        if self.silent_topics():
            return Health.WARN, f'silent: {", ".join(self.silent_topics())}', values
        return Health.OK, f'recording into {writer.directory}', values

    def check_silence(self):
        """A matched topic that stays silent is logged once: its publisher sends nothing, or
        the transport delivers nothing (Fast DDS shared memory to a recorder started right
        after one was killed -9 on this host: docs/reliability.md)."""
        if self.silence_warning <= 0.0:
            return
        now = time.monotonic()
        for topic, subscription in self.subscribed.items():
            if topic in self.silence_warned or self.writer.topic_counts.get(topic):
                continue
            publishers = subscription.get_publisher_count()
            if not publishers:
                self.matched_since.pop(topic, None)
                continue
            # The clock starts at the match, not the subscription: a publisher that appears
            # late and sends at once is not silent.
            if now - self.matched_since.setdefault(topic, now) < self.silence_warning:
                continue
            self.silence_warned.add(topic)
            self.get_logger().warning(
                f'no message on {topic} for {self.silence_warning:g} s although {publishers} '
                'publisher(s) are matched: a silent publisher, or a transport that delivers '
                'nothing (after a kill -9 on this host, restart with '
                'FASTDDS_BUILTIN_TRANSPORTS=UDPv4)')

    def close(self):
        if self.context.ok():          # publishers that appeared since the last timer tick
            for topic in list(self.writer.qos_pending):
                self.learn_qos(topic)
        self.writer.close()
        counts = ', '.join(f'{t}: {n}' for t, n in self.writer.topic_counts.items())
        print(f'[tsr_recorder] bag {self.writer.directory} closed: '
              f'{self.writer.message_count} messages ({counts})', flush=True)


def drain(node, executor):
    """After a stop signal: write what the DDS readers still hold (acknowledged to the
    publishers, so it must reach the bag) before the bag closes."""
    spin_until_quiet(executor, lambda: node.writer.message_count)


def main(args=None):
    return run_node(RecorderNode, on_exit=RecorderNode.close, args=args, drain=drain)


if __name__ == '__main__':
    sys.exit(main())
