"""Stock bags in, stock bags out: a bag written as rosbag2 0.26 (Jazzy) writes one
(`rosbag2_style`, written from the rosbag2 source at tag 0.26.5) reads back as the loop, with
`bag info` and with rosbags; and the project's writer stores what rosbag2 stores."""

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from tsr_sim import dynamics
from tsr_sim.units import Scale
import yaml

from conftest import ROOT

from tsr_koopman_ctrl import bag
from tsr_koopman_ctrl.bag import definitions, writer as bag_writer
from tsr_koopman_ctrl.learning import recorded
from tsr_koopman_ctrl.commands import bag as bag_tool

import rosbag2_style

SCALE = Scale(orbit_rate=1.0e-3, tether_length=50.0e3, mass=35.0)
H = dynamics.PAPER_STEP


def simulator_info():
    return {'mode': 'lockstep', 'step': H, 'substeps': 10,
            'scale': {'orbit_rate': SCALE.orbit_rate, 'tether_length': SCALE.tether_length,
                      'mass': SCALE.mass},
            'max_tension': SCALE.u_to_tension(dynamics.TENSION_LIMIT)}


def plant_loop(n, seed):
    """A loop the dynamics ran, near the equilibrium, tension 3 +- 0.5: (x, u, excitation)."""
    rng = np.random.default_rng(seed)
    excitation = rng.choice([-0.5, 0.5], n)
    u = 3.0 + excitation
    x = dynamics.rollout(rng.uniform(-0.05, 0.05, (1, 4)), u[None], H, 10)[0][:n]
    return x, u, excitation


def stock_bag(directory, n=70, seed=1, **options):
    """A stock rosbag2 bag of a lockstep loop; returns (path, x, u)."""
    x, u, excitation = plant_loop(n, seed)
    messages = rosbag2_style.loop_messages(
        SCALE.state_to_si(x), SCALE.u_to_tension(u), np.arange(n), simulator_info(),
        {'controller': 'linear_lqr'}, SCALE.u_to_tension(excitation))
    return rosbag2_style.write_loop_bag(directory, messages, **options), x, u


@pytest.fixture(scope='module')
def stock(tmp_path_factory):
    return stock_bag(tmp_path_factory.mktemp('stock') / 'rosbag2_2025_01_01-00_00_00')


def test_the_stock_bag_is_laid_out_as_rosbag2_writes_it(stock):
    """What the reader faces: schemas spelled 'MSG: std_msgs/Header' after a blank line,
    sequence 0, publish time before log time, two 'rosbag2' records holding only
    serialized_metadata, no chunk compression or CRC, metadata.yaml in yaml-cpp's style."""
    path = stock[0]
    with open(path / f'{path.name}_0.mcap', 'rb') as f:
        reader = make_reader(f)
        header = reader.get_header()
        schemas = {s.name: s.data.decode() for s in reader.get_summary().schemas.values()}
        messages = [m for _, _, m in reader.iter_messages()]
        records = list(reader.iter_metadata())
    assert (header.profile, header.library) == ('ros2', 'libmcap 1.3.0')
    assert '\n\n' + '=' * 80 + '\nMSG: std_msgs/Header\n' in schemas['tsr_msgs/msg/TsrState']
    assert {m.sequence for m in messages} == {0}
    assert all(m.log_time - m.publish_time == 40_000 for m in messages)
    assert [r.name for r in records] == ['rosbag2', 'rosbag2']
    assert all(list(r.metadata) == ['serialized_metadata'] for r in records)
    opened, closed = (yaml.safe_load(r.metadata['serialized_metadata']) for r in records)
    assert opened['message_count'] == 0 and opened['starting_time'] == {
        'nanoseconds_since_epoch': 2 ** 63 - 1}
    assert closed['message_count'] == len(messages) and closed['ros_distro'] == 'jazzy'
    text = (path / 'metadata.yaml').read_text()
    assert text.startswith('rosbag2_bagfile_information:\n  version: 9\n')
    assert '\n  topics_with_message_count:\n    - topic_metadata:\n        name: /tsr/state\n' \
        in text and '\n  compression_format: ""\n' in text and '\n  custom_data: ~\n' in text
    assert yaml.safe_load(text)['rosbag2_bagfile_information'] == closed


def test_read_loop_reads_a_stock_bag(stock):
    path, x, u = stock
    loop = bag.read_loop(path)
    np.testing.assert_array_equal(loop.step, np.arange(len(x)))
    np.testing.assert_allclose(loop.x, x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(loop.u, u, rtol=0, atol=1e-12)
    assert loop.scale == SCALE and loop.report.summary() == (
        f'{path.name}_0.mcap: complete, {3 * len(x) + 2} messages')


def test_bag_info_reads_a_stock_bag(stock, capsys):
    path, x, _ = stock
    assert bag_tool.main(['info', str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert f'messages:   {3 * len(x) + 2}' in lines
    assert '  /tsr/state        tsr_msgs/msg/TsrState  70' in lines
    assert lines[-1] == f'metadata.yaml: 1 files, {3 * len(x) + 2} messages'


def test_rosbags_reads_the_stock_bag(stock):
    """The independent reader agrees on what the stock-style helper wrote."""
    path, x, _ = stock
    typestore = get_typestore(Stores.ROS2_JAZZY)
    msg_dir = ROOT / 'ros2_ws' / 'src' / 'tsr_msgs' / 'msg'
    typestore.register(get_types_from_msg((msg_dir / 'TsrState.msg').read_text(),
                                          'tsr_msgs/msg/TsrState'))
    with AnyReader([path], default_typestore=typestore) as reader:
        states = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()
                  if c.topic == '/tsr/state']
        assert {c.digest for c in reader.connections if c.topic == '/tsr/state'} == {
            definitions.type_hash('tsr_msgs/msg/TsrState')}
    np.testing.assert_allclose([s.length for s in states], SCALE.state_to_si(x)[:, 2])


@pytest.mark.parametrize('hashes', [True, False])
def test_windows_of_a_stock_bag_with_or_without_type_hashes(tmp_path, hashes):
    """With hashes the types match by hash; without, by the normalised definition."""
    path, x, u = stock_bag(tmp_path / 'b', type_hashes=hashes)
    windows = recorded.read_windows(path, steps=30, h=H, state_dim=4)
    assert len(windows.data) == 2 and windows.warnings == []
    np.testing.assert_allclose(windows.data.x[1], x[30:61], rtol=0, atol=1e-12)
    np.testing.assert_allclose(windows.data.u[1], u[30:60], rtol=0, atol=1e-12)


def test_a_stock_bag_of_another_definition_is_refused_in_one_line(tmp_path, monkeypatch):
    """A genuinely different TsrState (a field added) recorded by stock rosbag2."""
    original = rosbag2_style.installed_msg

    def changed(package, name):
        text = original(package, name)
        return text + 'float64 extra\n' if name == 'TsrState' else text
    monkeypatch.setattr(rosbag2_style, 'installed_msg', changed)
    monkeypatch.setattr(rosbag2_style.full_text, '__defaults__', (changed,))
    path, _, _ = stock_bag(tmp_path / 'b', type_hashes=False)
    with pytest.raises(recorded.BagDataError) as caught:
        recorded.read_windows(path, steps=30)
    assert str(caught.value) == (
        f'{path}: tsr_msgs/msg/TsrState was recorded with another message definition than the '
        "installed one (tsr_msgs/TsrState declaration 11: 'float64 extra' in the bag, nothing "
        'installed)')


def test_the_project_writer_stores_times_and_metadata_as_rosbag2(tmp_path):
    """`write_received`: log time the reception, publish time the source timestamp, sequence
    0 (rosbag2 0.26's mcap_storage.cpp and recorder.cpp); a reception earlier than the message
    before it is logged at that message's time (log times never go back). The 'rosbag2' record
    holds the metadata without metadata.yaml's wrapper, as rosbag2 reads it."""
    info = {'source_timestamp': 1_000, 'received_timestamp': 5_000,
            'publication_sequence_number': 7, 'reception_sequence_number': 9}
    with bag.BagWriter(str(tmp_path / 'b')) as writer:
        writer.add_topic(bag.TopicInfo('/s', 'tsr_msgs/msg/TsrState',
                                       definitions.message_definition('tsr_msgs/msg/TsrState'),
                                       definitions.type_hash('tsr_msgs/msg/TsrState')))
        writer.write_received('/s', b'\x00\x01\x00\x00', info)
        writer.write_received('/s', b'\x00\x01\x00\x00', {**info, 'received_timestamp': 4_000})
        writer.write_received('/s', b'\x00\x01\x00\x00',
                              {'source_timestamp': 0, 'received_timestamp': 0})
    with open(tmp_path / 'b' / 'b_0.mcap', 'rb') as f:
        reader = make_reader(f)
        messages = [m for _, _, m in reader.iter_messages()]
        (record,) = reader.iter_metadata()
    assert [(m.sequence, m.log_time, m.publish_time) for m in messages[:2]] == [
        (0, 5_000, 1_000), (0, 5_000, 1_000)]
    assert messages[2].log_time == messages[2].publish_time > 10 ** 18      # now
    assert list(record.metadata) == ['serialized_metadata']
    stored = yaml.safe_load(record.metadata['serialized_metadata'])
    assert stored['version'] == 9 and stored['message_count'] == 3
    assert stored == yaml.safe_load((tmp_path / 'b' / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']


def test_the_received_callback_takes_the_message_info_either_way_executors_pass_it():
    """rclpy asks for the info when the callback binds two arguments, not one; the Jazzy
    EventsExecutor passes the (msg, info) pair as one argument, the other executors as two."""
    import inspect
    got = []
    callback = bag_writer.ReceivedCallback(lambda msg, info: got.append((msg, info)))
    with pytest.raises(TypeError):
        inspect.signature(callback).bind(object())
    inspect.signature(callback).bind(object(), object())
    callback(b'a', {'received_timestamp': 1})
    callback((b'b', {'received_timestamp': 2}))
    assert got == [(b'a', {'received_timestamp': 1}), (b'b', {'received_timestamp': 2})]
