"""A bag written the way stock `ros2 bag record -s mcap` of Jazzy (rosbag2 0.26) writes one.

A test reference, written from the rosbag2 source (ros2/rosbag2, tag 0.26.5, commit
6927adf585cd99b8b6c2f93c87fce668b2fc64cf), not from the project's writer:

- schema text: `LocalMessageDefinitionSource::get_full_text` in
  rosbag2_cpp/src/rosbag2_cpp/message_definitions/local_message_definition_source.cpp: the .msg
  file's text, then per dependency (a std::set: name order; named as the field spells it)
  '\\n', 80 '=', '\\nMSG: ', the name, '\\n' and its text, depth first, each once.
- rosbag2_storage_mcap/src/mcap_storage.cpp: `open_impl` (profile 'ros2', no compression, no
  chunk CRC), `create_topic` (one schema per type, encoding ros2msg; a channel per topic, cdr,
  metadata `offered_qos_profiles` (YAML of the QoS list, version 9) and `topic_type_hash`),
  `write_lock_free` (sequence 0, log time = recv_timestamp, publish time = send_timestamp),
  `update_metadata` (a 'rosbag2' metadata record, one key 'serialized_metadata': the
  BagMetadata YAML, no wrapper).
- rosbag2_cpp/src/rosbag2_cpp/writers/sequential_writer.cpp: `update_metadata` at open (start
  time 'max', no topics) and at close (`finalize_metadata`), then metadata.yaml
  (rosbag2_storage/src/rosbag2_storage/metadata_io.cpp: the same YAML under
  'rosbag2_bagfile_information'; fields as rosbag2_storage/include/rosbag2_storage/yaml.hpp
  encodes them, in yaml-cpp's block style).
- rosbag2_transport/src/rosbag2_transport/recorder.cpp `create_subscription`: recv_timestamp
  is the rmw's received_timestamp, send_timestamp its source_timestamp.
- the MCAP library it vendors (mcap_vendor: foxglove/mcap releases/cpp/v1.3.0,
  cpp/mcap/include/mcap/writer.inl): library 'libmcap 1.3.0', 768 KiB chunks, a schema and a
  channel written just before their first message.

Where the Python mcap writer cannot follow: channel ids are given in first-message order (not
creation order), a topic without messages gets its channel in the last chunk (not only in the
summary), and the summary has no CRC. No reader depends on either.
"""

import os
import re

from mcap.writer import CompressionType, Writer

MCAP_LIBRARY = 'libmcap 1.3.0'
CHUNK_SIZE = 1024 * 768
#: `std::chrono::nanoseconds::max()`: the start time before any message.
NEVER = 2 ** 63 - 1
_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_PACKAGE_TYPENAME = re.compile(r'^([a-zA-Z0-9_]+)/(?:msg/|srv/)?([a-zA-Z0-9_]+)$')
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
               'int32', 'uint32', 'int64', 'uint64', 'string'}


def installed_msg(package, name):
    from ament_index_python.packages import get_package_share_directory
    with open(os.path.join(get_package_share_directory(package), 'msg', name + '.msg')) as f:
        return f.read()


def full_text(root_type, read=installed_msg):
    """`get_full_text(root_type)` for a message type; `read(package, Type)` -> .msg text."""
    seen = set()

    def spec(type_name):
        package, name = _PACKAGE_TYPENAME.match(type_name).groups()
        text = read(package, name)
        dependencies = set()
        for match in _FIELD_TYPE.finditer(text):
            found = match.group(1)
            if found not in _PRIMITIVES:
                dependencies.add(found if '/' in found else f'{package}/{found}')
        return text, sorted(dependencies)

    def append_recursive(type_name):
        text, dependencies = spec(type_name)
        result = text
        for dep in dependencies:
            if dep not in seen:
                seen.add(dep)
                result += '\n' + '=' * 80 + '\n' + 'MSG: ' + dep + '\n'
                result += append_recursive(dep)
        return result

    return append_recursive(root_type)


def emit(value, indent=0):
    """YAML as yaml-cpp's emitter writes a node in block style (mappings in insertion order)."""
    pad = ' ' * indent
    lines = []
    for key, item in value.items():
        if isinstance(item, dict) and item:
            lines.append(f'{pad}{key}:\n{emit(item, indent + 2)}')
        elif isinstance(item, list) and item:
            lines.append(f'{pad}{key}:\n{_emit_list(item, indent + 2)}')
        else:
            lines.append(f'{pad}{key}: {_scalar(item)}')
    return '\n'.join(lines)


def _emit_list(items, indent):
    pad = ' ' * indent
    out = []
    for item in items:
        if isinstance(item, dict):
            body = emit(item, indent + 2)
            out.append(f'{pad}- {body[indent + 2:]}')
        else:
            out.append(f'{pad}- {_scalar(item)}')
    return '\n'.join(out)


def _scalar(value):
    if value is None or value == {}:
        return '~'
    if value == []:
        return '[]'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if value == '':
        return '""'
    return str(value)


class Rosbag2StyleBag:
    """`ros2 bag record -s mcap` into `directory`: create_topic, write(recv, send), close."""

    def __init__(self, directory, ros_distro='jazzy'):
        os.makedirs(directory)
        self.directory = str(directory)
        name = os.path.basename(os.path.normpath(self.directory))
        self.file = f'{name}_0.mcap'
        self.ros_distro = ros_distro
        self.topics = {}           # name -> [type, qos list, hash, count]
        self.schemas, self.channels = {}, {}
        self.start = self.file_start = NEVER
        self.end = None
        self.count = 0
        self.final = False
        self._stream = open(os.path.join(self.directory, self.file), 'wb')
        self._writer = Writer(self._stream, chunk_size=CHUNK_SIZE,
                              compression=CompressionType.NONE, enable_crcs=False)
        self._writer.start(profile='ros2', library=MCAP_LIBRARY)
        self._update_metadata()    # SequentialWriter::open: the metadata of an empty bag

    def create_topic(self, name, type_name, offered_qos, type_hash):
        self.topics[name] = [type_name, list(offered_qos), type_hash, 0]

    def write(self, topic, data, recv_ns, send_ns):
        channel = self.channels.get(topic) or self._channel(topic)
        self._writer.add_message(channel, log_time=recv_ns, data=bytes(data),
                                 publish_time=send_ns, sequence=0)
        self.topics[topic][3] += 1
        self.count += 1
        self.start, self.file_start = min(self.start, recv_ns), min(self.file_start, recv_ns)
        self.end = recv_ns if self.end is None else max(self.end, recv_ns)

    def close(self):
        for topic in self.topics:
            if topic not in self.channels:
                self._channel(topic)
        self.final = True          # SequentialWriter::finalize_metadata: the topics and counts
        self._update_metadata()
        self._writer.finish()
        self._stream.close()
        with open(os.path.join(self.directory, 'metadata.yaml'), 'w') as f:
            f.write(emit({'rosbag2_bagfile_information': self.metadata()}) + '\n')

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _channel(self, topic):
        type_name, qos, type_hash, _ = self.topics[topic]
        if type_name not in self.schemas:
            self.schemas[type_name] = self._writer.register_schema(
                type_name, 'ros2msg', full_text(type_name).encode())
        self.channels[topic] = self._writer.register_channel(
            topic, 'cdr', self.schemas[type_name],
            {'offered_qos_profiles': _emit_list(qos, 0) if qos else '[]',
             'topic_type_hash': type_hash})
        return self.channels[topic]

    def _update_metadata(self):
        self._writer.add_metadata('rosbag2', {'serialized_metadata': emit(self.metadata())})

    def metadata(self):
        duration = 0 if self.end is None else self.end - self.start
        return {
            'version': 9, 'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': self.start},
            'message_count': self.count,
            'topics_with_message_count': [
                {'topic_metadata': {'name': name, 'type': type_name,
                                    'serialization_format': 'cdr',
                                    'offered_qos_profiles': qos,
                                    'type_description_hash': type_hash},
                 'message_count': count}
                for name, (type_name, qos, type_hash, count) in self.topics.items()
            ] if self.final else [],
            'compression_format': '', 'compression_mode': '',
            'relative_file_paths': [self.file],
            'files': [{'path': self.file,
                       'starting_time': {'nanoseconds_since_epoch': self.file_start},
                       'duration': {'nanoseconds': duration}, 'message_count': self.count}],
            'custom_data': None, 'ros_distro': self.ros_distro}


def loop_messages(x_si, tension, steps, simulator, controller, excitation=None):
    """(topic, serialized message) of a lockstep loop as its nodes publish it (rclpy classes,
    `tsr_sim.wire`): the two RunInfo, then per step its state, its command and its excitation.
    `x_si` (N, 4) SI states, `tension` (N,) [N] (NaN: no command), `excitation` (N,) [N]."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import serialize_message
    from tsr_msgs.msg import Excitation
    from tsr_sim import wire
    out = [('/tsr/run_info', wire.run_info_msg('/simulator', 'simulator', simulator, Time())),
           ('/tsr/run_info', wire.run_info_msg('/controller', 'controller', controller,
                                               Time()))]
    h_seconds = simulator['step'] / simulator['scale']['orbit_rate']
    for i, step in enumerate(steps):
        seconds = float(step) * h_seconds
        stamp = Time(sec=int(seconds), nanosec=int(round((seconds % 1) * 1e9)) % 10 ** 9)
        out.append(('/tsr/state', wire.state_to_msg(x_si[i], step, stamp)))
        if tension[i] == tension[i]:
            out.append(('/tsr/tension_cmd', wire.tension_msg(tension[i], step, stamp)))
            if excitation is not None:
                added = Excitation(step=int(step), tension=float(excitation[i]))
                added.header.stamp = stamp
                out.append(('/tsr/excitation', added))
    return [(topic, serialize_message(msg)) for topic, msg in out]


def write_loop_bag(directory, messages, type_hashes=True, start_ns=1_700_000_000_000_000_000):
    """A stock bag of `messages` ((topic, CDR) from `loop_messages`), received 1 ms apart and
    each sent 40 us before; the topics with the QoS the loop's publishers offer and, unless
    `type_hashes` is False, the installed type hash (what the publishers announce)."""
    from tsr_sim import wire
    from tsr_koopman_ctrl.bag import definitions
    reliable = definitions.qos_dict(1, 10, 1, 1, 1, 2 ** 63 - 1, 2 ** 63 - 1, 2 ** 63 - 1)
    with Rosbag2StyleBag(directory) as bag:
        for name in ('tsr/state', 'tsr/tension_cmd', 'tsr/run_info', 'tsr/excitation'):
            type_name = wire.LOOP_TOPIC_TYPES[name]
            bag.create_topic(wire.resolve(name), type_name, [reliable],
                             definitions.type_hash(type_name) if type_hashes else '')
        for i, (topic, data) in enumerate(messages):
            recv = start_ns + 1_000_000 * i
            bag.write(topic, data, recv, recv - 40_000)
    return directory
