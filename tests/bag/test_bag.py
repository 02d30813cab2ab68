"""The bag writer and reader, ROS-free, checked against the independent rosbags reader."""

import dataclasses
import os

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
from tsr_sim import wire
import yaml

from tsr_koopman_ctrl import bag
from tsr_koopman_ctrl.bag import definitions

import rosbag2_style

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
HEADER_DEFS = {
    'test_pkg/msg/Stamped': '# a stamped float\nstd_msgs/Header header\nfloat64 value  # [m]\n'
                            'uint8 CONST=3\nbuiltin_interfaces/Time[] times\n',
    'std_msgs/msg/Header': 'builtin_interfaces/Time stamp\nstring frame_id\n',
    'builtin_interfaces/msg/Time': 'int32 sec\nuint32 nanosec\n',
}
QOS = [definitions.qos_dict(1, 10, 1, 2, 1, None, None, None)]


def string_topic(name='/chatter'):
    # Definition and hash from the installed std_msgs: rosbags recomputes and checks the hash.
    type_name = 'std_msgs/msg/String'
    return bag.TopicInfo(name, type_name, definitions.message_definition(type_name),
                         definitions.type_hash(type_name), QOS)


def cdr_string(text):
    msg = TYPESTORE.types['std_msgs/msg/String'](data=text)
    return bytes(TYPESTORE.serialize_cdr(msg, 'std_msgs/msg/String'))


def write_strings(directory, n, **kw):
    with bag.BagWriter(str(directory), **kw) as writer:
        writer.add_topic(string_topic())
        for i in range(n):
            writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=1_000_000 * (i + 1))
    return writer


def test_definition_is_spelled_as_rosbag2_spells_it():
    """rosbag2 0.26 (local_message_definition_source.cpp, tag 0.26.5): each dependency once,
    in name order (a std::set), after a blank line, the separator and 'MSG: ' with the name as
    the field spells it; the texts unchanged. The reference is tests/bag/rosbag2_style.py."""
    text = definitions.message_definition('test_pkg/msg/Stamped', HEADER_DEFS.__getitem__)
    sep = '=' * 80
    assert text == (HEADER_DEFS['test_pkg/msg/Stamped']
                    + f'\n{sep}\nMSG: builtin_interfaces/Time\n'
                    + HEADER_DEFS['builtin_interfaces/msg/Time']
                    + f'\n{sep}\nMSG: std_msgs/Header\n' + HEADER_DEFS['std_msgs/msg/Header'])
    assert text == rosbag2_style.full_text(
        'test_pkg/msg/Stamped', lambda package, name: HEADER_DEFS[f'{package}/msg/{name}'])
    for type_name in wire.LOOP_TOPIC_TYPES.values():
        assert definitions.message_definition(type_name) == rosbag2_style.full_text(type_name)


def test_round_trip_with_own_reader_and_rosbags(tmp_path):
    path = tmp_path / 'b'
    write_strings(path, 500)
    reader = bag.BagReader(str(path))
    got = [m for m, _ in zip(reader.decoded(), range(10**6))]
    assert [d.data for _, d in got] == [f'msg {i}' for i in range(500)]
    assert reader.report.messages == 500 and not reader.report.recovered
    assert reader.report.summary() == 'b_0.mcap: complete, 500 messages'

    meta = yaml.safe_load(open(path / 'metadata.yaml'))['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['message_count'] == 500
    with AnyReader([path], default_typestore=TYPESTORE) as other:
        conn = other.connections[0]
        assert conn.topic == '/chatter' and conn.msgtype == 'std_msgs/msg/String'
        texts = [other.deserialize(raw, c.msgtype).data for c, _, raw in other.messages()]
        assert conn.ext.offered_qos_profiles[0].depth == 10
    assert texts == [f'msg {i}' for i in range(500)]


def test_the_reader_gives_each_message_its_log_and_publish_times(tmp_path):
    """The log and publish times come back, each as written."""
    with bag.BagWriter(str(tmp_path / 'b')) as writer:
        writer.add_topic(string_topic())
        writer.write('/chatter', cdr_string('one'), log_time_ns=8_470_000_000,
                     publish_time_ns=1_796_400_000_000_000_000)
        writer.write('/chatter', cdr_string('two'), log_time_ns=16_940_000_000)
    got = [(m.log_time_ns, m.publish_time_ns) for m in bag.BagReader(str(tmp_path / 'b'))
           .messages()]
    assert got == [(8_470_000_000, 1_796_400_000_000_000_000), (16_940_000_000, 16_940_000_000)]


def test_split_by_size_keeps_every_message_in_order(tmp_path):
    writer = write_strings(tmp_path / 'b', 3000, max_file_bytes=8_000, chunk_size=2_000)
    assert len(writer.files) > 2
    reader = bag.BagReader(str(tmp_path / 'b'))
    times = [m.log_time_ns for m in reader.messages()]
    assert times == [1_000_000 * (i + 1) for i in range(3000)]
    with AnyReader([tmp_path / 'b'], default_typestore=TYPESTORE) as other:
        assert sum(1 for _ in other.messages()) == 3000


def test_split_by_duration(tmp_path):
    writer = write_strings(tmp_path / 'b', 100, max_file_seconds=0.01)   # 10 ms per file
    assert len(writer.files) == 10 and all(f.count == 10 for f in writer.files)


def test_truncated_file_is_recovered_up_to_the_last_complete_chunk(tmp_path):
    path = tmp_path / 'b'
    write_strings(path, 2000, chunk_size=4_000)
    mcap_file = path / 'b_0.mcap'
    data = mcap_file.read_bytes()
    mcap_file.write_bytes(data[:len(data) // 2])     # what a SIGKILL leaves behind
    reader = bag.BagReader(str(path))
    texts = [d.data for _, d in reader.decoded()]
    assert reader.report.recovered and reader.report.truncated == ['b_0.mcap']
    assert reader.report.summary() == f'b_0.mcap: truncated: {len(texts)} messages recovered'
    assert 500 < len(texts) < 2000
    assert texts == [f'msg {i}' for i in range(len(texts))]   # a prefix, in order


def test_writer_refuses_a_non_empty_directory(tmp_path):
    (tmp_path / 'b').mkdir()
    (tmp_path / 'b' / 'x').write_text('keep me')
    with pytest.raises(FileExistsError, match='not empty'):
        bag.BagWriter(str(tmp_path / 'b'))
    assert os.listdir(tmp_path / 'b') == ['x']


def test_missing_bag_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match='no bag at'):
        bag.BagReader(str(tmp_path / 'nothing'))


def channels_qos(path):
    """topic -> offered_qos_profiles of the channels in an MCAP file's summary."""
    with open(path, 'rb') as f:
        return {c.topic: c.metadata['offered_qos_profiles']
                for c in make_reader(f).get_summary().channels.values()}


def test_a_topic_added_before_its_qos_is_known_gets_it_in_channel_and_metadata(tmp_path):
    """A channel cannot change once written: a topic whose offered QoS is pending is listed in
    metadata.yaml at once, and its channel waits for the QoS, its first message or the close."""
    path = tmp_path / 'b'
    writer = bag.BagWriter(str(path))
    for name in ('/learnt', '/early', '/never'):
        writer.add_topic(dataclasses.replace(string_topic(name), offered_qos=[]),
                         qos_pending=True)
    meta = yaml.safe_load(open(path / 'metadata.yaml'))['rosbag2_bagfile_information']
    assert [t['topic_metadata']['name'] for t in meta['topics_with_message_count']] == [
        '/learnt', '/early', '/never']
    writer.set_offered_qos('/learnt', QOS)
    writer.write('/early', cdr_string('before any QoS'), log_time_ns=1)    # not held back
    writer.write('/learnt', cdr_string('after'), log_time_ns=2)
    with pytest.raises(ValueError, match='not waiting'):
        writer.set_offered_qos('/early', QOS)                          # its channel is written
    writer.close()
    expected = {'/learnt': yaml.safe_dump(QOS, sort_keys=False), '/early': '', '/never': ''}
    assert channels_qos(path / 'b_0.mcap') == expected
    meta = yaml.safe_load(open(path / 'metadata.yaml'))['rosbag2_bagfile_information']
    # metadata.yaml of version 9 holds the profiles as YAML, the channel as a string.
    assert {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles']
            for t in meta['topics_with_message_count']} == {
                '/learnt': QOS, '/early': [], '/never': []}
    with AnyReader([path], default_typestore=TYPESTORE) as other:
        qos = {c.topic: c.ext.offered_qos_profiles for c in other.connections}
        assert [(q.reliability.value, q.durability.value, q.depth) for q in qos['/learnt']] == [
            (1, 2, 10)]
        assert [m.data for m in (other.deserialize(raw, c.msgtype)
                                 for c, _, raw in other.messages())] == ['before any QoS', 'after']


def test_offered_qos_is_written_as_rosbags_own_version_9_writer_writes_it(tmp_path):
    """The independent reference: rosbags' MCAP writer at metadata version 9 (what Jazzy's
    rosbag2 reads: policies by name, metadata.yaml holding the profiles as YAML)."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    from rosbags.rosbag2 import StoragePlugin, Writer
    infinite = QosTime(9223372036, 854775807)
    theirs = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE,
                 QosDurability.TRANSIENT_LOCAL, infinite, infinite, QosLiveliness.AUTOMATIC,
                 infinite, False)
    with Writer(tmp_path / 'rosbags', version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection('/chatter', 'std_msgs/msg/String', typestore=TYPESTORE,
                              offered_qos_profiles=[theirs])
    never = 2 ** 63 - 1                   # rclpy's infinite Duration, in nanoseconds
    ours = definitions.qos_dict(1, 10, 1, 1, 1, never, never, never)
    with bag.BagWriter(str(tmp_path / 'ours')) as writer:
        writer.add_topic(dataclasses.replace(string_topic(), offered_qos=[ours]))

    def profiles(directory):
        meta = yaml.safe_load(open(directory / 'metadata.yaml'))['rosbag2_bagfile_information']
        (topic,) = meta['topics_with_message_count']
        (mcap,) = directory.glob('*.mcap')
        return (meta['version'], topic['topic_metadata']['offered_qos_profiles'],
                yaml.safe_load(channels_qos(mcap)['/chatter']))
    assert profiles(tmp_path / 'ours') == profiles(tmp_path / 'rosbags')
