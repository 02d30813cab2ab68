"""Nothing lost: the time-bounded flush, what the reader says about damaged files, and
`bag recover`/`bag info`, checked against what was written and against rosbags.

A kill -9 is simulated by copying the bag's files while the writer is still open: the copy holds
exactly the bytes the OS has, which is what a killed process leaves behind."""

import os
import shutil
import subprocess
import sys

from mcap.reader import make_reader
from mcap.records import Channel, Message
import pytest
from rosbags.highlevel import AnyReader
from test_bag import cdr_string, string_topic, TYPESTORE
import yaml

from tsr_koopman_ctrl import bag
from tsr_koopman_ctrl.bag import definitions, reader as bag_reader
from tsr_koopman_ctrl.commands import bag as bag_tool

INT_QOS = [definitions.qos_dict(1, 3, 2, 2, 1, None, None, None)]   # depth 3, best effort


class Clock:
    """A clock the test moves by hand."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def int_topic(name='/numbers'):
    type_name = 'std_msgs/msg/Int32'
    return bag.TopicInfo(name, type_name, definitions.message_definition(type_name),
                         definitions.type_hash(type_name), INT_QOS)


def cdr_int(value):
    msg = TYPESTORE.types['std_msgs/msg/Int32'](data=value)
    return bytes(TYPESTORE.serialize_cdr(msg, 'std_msgs/msg/Int32'))


def killed_copy(src, dst):
    """The bag as a kill -9 now would leave it (the writer stays open)."""
    shutil.copytree(src, dst)
    return dst


def kept_texts(path):
    """The messages our reader gets from a bag; [] for one it calls empty."""
    try:
        return [d.data for _, d in bag.BagReader(str(path)).decoded()]
    except ValueError as err:
        assert 'empty' in str(err)
        return []


def metadata(path):
    with open(os.path.join(path, 'metadata.yaml')) as f:
        return yaml.safe_load(f)['rosbag2_bagfile_information']


def chunk_indexes(path):
    with open(path, 'rb') as f:
        return make_reader(f).get_summary().chunk_indexes


# --------------------------------------------------------------------------- the writer

def test_metadata_lists_the_file_as_soon_as_the_writer_opens(tmp_path):
    writer = bag.BagWriter(str(tmp_path / 'b'))
    meta = metadata(tmp_path / 'b')
    assert meta['relative_file_paths'] == ['b_0.mcap'] and meta['message_count'] == 0
    assert (tmp_path / 'b' / 'b_0.mcap').read_bytes().startswith(bag_reader.MAGIC)
    writer.add_topic(string_topic())
    topics = metadata(tmp_path / 'b')['topics_with_message_count']
    assert [t['topic_metadata']['name'] for t in topics] == ['/chatter']
    with pytest.raises(ValueError, match=r'b_0\.mcap: empty'):
        bag.BagReader(str(tmp_path / 'b'))     # an MCAP file, with nothing in it yet
    writer.close()


@pytest.mark.parametrize('period', [1.0, 0.3])
def test_a_kill_loses_at_most_the_flush_period(tmp_path, period):
    clock, spacing, n = Clock(), 0.13, 120
    path = tmp_path / 'b'
    writer = bag.BagWriter(str(path), chunk_size=1 << 20, flush_period=period, clock=clock)
    writer.add_topic(string_topic())
    times = []
    for i in range(n):
        clock.now = spacing * i
        writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=int(clock.now * 1e9))
        times.append(clock.now)
        if i % 7 == 3:
            copy = killed_copy(path, tmp_path / f'kill{i}' / 'b')
            kept = kept_texts(copy)
            assert kept == [f'msg {j}' for j in range(len(kept))]         # a prefix, in order
            lost = times[len(kept):]
            assert all(t > clock.now - period for t in lost), (i, len(lost))
            assert metadata(copy)['message_count'] == len(kept)           # rewritten at flush
    writer.close()
    # Not flushed more often than needed either: each chunk but the last spans one period.
    spans = [(c.message_end_time - c.message_start_time) / 1e9
             for c in chunk_indexes(path / 'b_0.mcap')]
    assert len(spans) > 5
    assert all(period <= s < period + spacing for s in spans[:-1]), spans


def test_without_flush_period_a_kill_loses_the_whole_chunk(tmp_path):
    clock = Clock()
    writer = bag.BagWriter(str(tmp_path / 'b'), flush_period=0, clock=clock)
    writer.add_topic(string_topic())
    for i in range(50):
        clock.now = 0.5 * i
        writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=i + 1)
    assert kept_texts(killed_copy(tmp_path / 'b', tmp_path / 'kill' / 'b')) == []
    writer.close()


def test_flush_if_due_flushes_an_idle_stream(tmp_path):
    clock = Clock()
    writer = bag.BagWriter(str(tmp_path / 'b'), flush_period=1.0, clock=clock)
    writer.add_topic(string_topic())
    for i in range(3):
        writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=i + 1)
    assert not writer.flush_if_due(0.99)
    assert kept_texts(killed_copy(tmp_path / 'b', tmp_path / 'k1' / 'b')) == []
    assert writer.flush_if_due(1.0)
    assert kept_texts(killed_copy(tmp_path / 'b', tmp_path / 'k2' / 'b')) == [
        'msg 0', 'msg 1', 'msg 2']
    assert not writer.flush_if_due(50.0)      # nothing waiting: nothing to do
    clock.now = 2.0
    writer.write('/chatter', cdr_string('msg 3'), log_time_ns=4)
    assert not writer.flush_if_due() and writer.flush_if_due(3.0)
    writer.close()


def test_a_chunk_filled_by_size_reaches_the_file_at_once(tmp_path):
    chunk, n = 2_000, 1_000
    writer = bag.BagWriter(str(tmp_path / 'b'), chunk_size=chunk, flush_period=0)
    writer.add_topic(string_topic())
    record = 9 + 22 + len(cdr_string('msg 000'))    # opcode, length, message header, data
    for i in range(n):
        writer.write('/chatter', cdr_string(f'msg {i:03d}'), log_time_ns=i + 1)
        if i % 50 == 49:     # kill at many points: Python's own buffer must never hold a chunk
            kept = kept_texts(killed_copy(tmp_path / 'b', tmp_path / f'kill{i}' / 'b'))
            assert kept == [f'msg {j:03d}' for j in range(len(kept))]
            assert i + 1 - len(kept) <= chunk // record + 1, i    # only the chunk in progress
    writer.close()


# --------------------------------------------------------------------------- the reader

@pytest.mark.parametrize('content, says', [
    (b'', 'b_0.mcap: empty (0 bytes)'),
    (b'this is not a bag, just some text', 'b_0.mcap: not an MCAP file'),
    (bag_reader.MAGIC[:5], 'b_0.mcap: empty (5 bytes)'),
], ids=['zero_bytes', 'text', 'cut_in_the_magic'])
def test_a_bag_without_readable_messages_is_one_line_naming_the_file(tmp_path, content, says):
    (tmp_path / 'b').mkdir()
    (tmp_path / 'b' / 'b_0.mcap').write_bytes(content)
    with pytest.raises(ValueError) as err:
        bag.BagReader(str(tmp_path / 'b'))
    assert str(err.value) == f'no readable messages in {tmp_path / "b"}: {says}'


def test_a_file_killed_before_its_first_chunk_is_empty_not_recovered(tmp_path):
    write = bag.BagWriter(str(tmp_path / 'b'), flush_period=0)
    write.add_topic(string_topic())
    write.write('/chatter', cdr_string('lost'), log_time_ns=1)
    with pytest.raises(ValueError, match=r'b_0\.mcap: empty \(no complete chunk in \d+ bytes'):
        bag.BagReader(str(killed_copy(tmp_path / 'b', tmp_path / 'kill' / 'b')))
    write.close()
    closed_empty = bag.BagWriter(str(tmp_path / 'c'))
    closed_empty.add_topic(string_topic())
    closed_empty.close()
    with pytest.raises(ValueError, match=r'c_0\.mcap: empty \(no messages\)$'):
        bag.BagReader(str(tmp_path / 'c'))


def test_a_bad_file_next_to_good_ones_is_reported_not_fatal(tmp_path):
    path = tmp_path / 'b'
    with bag.BagWriter(str(path)) as writer:
        writer.add_topic(string_topic())
        for i in range(100):
            writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=i + 1)
    (path / 'b_1.mcap').write_bytes(b'garbage' * 10)
    reader = bag.BagReader(str(path))
    assert [d.data for _, d in reader.decoded()] == [f'msg {i}' for i in range(100)]
    assert reader.report.summary().splitlines() == [
        'b_0.mcap: complete, 100 messages', 'b_1.mcap: not an MCAP file']
    assert not reader.report.recovered


def test_a_damaged_chunk_keeps_the_chunks_before_it(tmp_path):
    path = tmp_path / 'b'
    with bag.BagWriter(str(path), chunk_size=4_000) as writer:
        writer.add_topic(string_topic())
        for i in range(2000):
            writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=i + 1)
    mcap_file = path / 'b_0.mcap'
    bad = chunk_indexes(mcap_file)[3]
    before = bad.message_start_time - 1     # log times are 1..2000, one per message
    data = bytearray(mcap_file.read_bytes())
    data[bad.chunk_start_offset + bad.chunk_length // 2] ^= 0xFF
    mcap_file.write_bytes(bytes(data))
    reader = bag.BagReader(str(path))
    assert [d.data for _, d in reader.decoded()] == [f'msg {i}' for i in range(before)]
    line = reader.report.summary()
    assert line.startswith(f'b_0.mcap: corrupt (chunk record at byte {bad.chunk_start_offset}: ')
    assert line.endswith(f'): {before} messages recovered before it')
    assert reader.report.recovered and reader.report.truncated == []


def test_a_chunk_cut_short_gives_its_complete_blocks(tmp_path):
    path = tmp_path / 'b'
    with bag.BagWriter(str(path), chunk_size=1 << 20, flush_period=0) as writer:
        writer.add_topic(string_topic())
        for i in range(20_000):
            writer.write('/chatter', cdr_string(f'message number {i:05d}'), log_time_ns=i + 1)
    mcap_file = path / 'b_0.mcap'
    first = chunk_indexes(mcap_file)[0]
    cut = first.chunk_start_offset + int(first.chunk_length * 0.7)   # inside the chunk
    mcap_file.write_bytes(mcap_file.read_bytes()[:cut])
    reader = bag.BagReader(str(path))
    texts = [d.data for _, d in reader.decoded()]
    assert texts == [f'message number {i:05d}' for i in range(len(texts))]
    # At least one whole zstd block (128 KiB of ~58-byte records) out of the cut chunk.
    assert len(texts) >= (128 << 10) // 58 and len(texts) < 20_000
    assert reader.report.files[0].salvaged == len(texts)
    assert reader.report.summary() == (f'b_0.mcap: truncated: {len(texts)} messages recovered '
                                       f'({len(texts)} from a partly written chunk)')


# --------------------------------------------------------------------------- bag recover

def write_killed_bag(tmp_path, n=900, kill_at=700):
    """Two topics, split by size, killed (copied) after `kill_at` messages. Returns the killed
    bag and what was written: (topic, type, log time, value) per message."""
    clock = Clock()
    writer = bag.BagWriter(str(tmp_path / 'live' / 'b'), max_file_bytes=6_000, chunk_size=1_500,
                           flush_period=0.5, clock=clock)
    writer.add_topic(string_topic())
    writer.add_topic(int_topic())
    written = []
    for i in range(n):
        clock.now = 0.01 * i
        t = 1_700_000_000_000_000_000 + 1_000_000 * i
        if i % 3:
            writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=t,
                         publish_time_ns=t - 1000 - i)   # sent before received
            written.append(('/chatter', 'std_msgs/msg/String', t, f'msg {i}'))
        else:
            writer.write('/numbers', cdr_int(-i), log_time_ns=t)
            written.append(('/numbers', 'std_msgs/msg/Int32', t, -i))
        if i + 1 == kill_at:
            killed = killed_copy(tmp_path / 'live' / 'b', tmp_path / 'b')
    writer.close()
    return killed, written


def read_with_rosbags(path):
    with AnyReader([path], default_typestore=TYPESTORE) as reader:
        got = [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype).data)
               for c, t, raw in reader.messages()]
        connections = {c.topic: c for c in reader.connections}
    return got, connections


def raw_records(path):
    """(topic, sequence, log time, publish time, data) per message, as stored."""
    out = []
    for name in sorted(os.listdir(path)):
        if name.endswith('.mcap'):
            channels = {}
            for r in bag_reader.scan_file(os.path.join(path, name), bag_reader.FileReport(name)):
                if isinstance(r, Channel):
                    channels[r.id] = r.topic
                elif isinstance(r, Message):
                    out.append((channels[r.channel_id], r.sequence, r.log_time, r.publish_time,
                                r.data))
    return out


def test_recover_writes_a_complete_bag_of_exactly_the_kept_messages(tmp_path, capsys):
    killed, written = write_killed_bag(tmp_path)
    killed_reader = bag.BagReader(str(killed))
    kept = [(m.topic, m.type, m.log_time_ns, d.data) for m, d in killed_reader.decoded()]
    states = [f.state for f in killed_reader.report.files]
    assert len(states) > 2 and set(states[:-1]) == {'complete'} and states[-1] == 'truncated'
    assert kept == written[:len(kept)] and 700 - 50 <= len(kept) < 700   # 0.5 s of 10 ms
    before = {n: (killed / n).read_bytes() for n in os.listdir(killed)}

    out = tmp_path / 'fixed'
    assert bag_tool.main(['recover', str(killed), '--out', str(out)]) == 0
    line = capsys.readouterr().out
    counts = {topic: sum(k[0] == topic for k in kept) for topic in ('/chatter', '/numbers')}
    assert line.count('\n') == 1 and line.startswith(
        f'kept {len(kept)} messages (/chatter {counts["/chatter"]}, /numbers '
        f'{counts["/numbers"]}) in {out}, from b_0.mcap: complete, ')
    assert line.rstrip().endswith(killed_reader.report.files[-1].line())

    got, connections = read_with_rosbags(out)
    assert got == kept
    for topic, depth in (('/chatter', 10), ('/numbers', 3)):
        conn = connections[topic]
        assert conn.msgcount == counts[topic]
        assert conn.digest == definitions.type_hash(conn.msgtype) != ''
        assert conn.ext.offered_qos_profiles[0].depth == depth
    fixed = bag.BagReader(str(out))
    assert [(m.topic, m.type, m.log_time_ns, d.data) for m, d in fixed.decoded()] == kept
    assert {f.state for f in fixed.report.files} == {'complete'}
    assert raw_records(out) == raw_records(killed)      # sequence, publish time, bytes too

    meta = metadata(out)
    assert meta['message_count'] == len(kept)
    assert {t['topic_metadata']['name']: t['message_count']
            for t in meta['topics_with_message_count']} == counts
    assert meta['relative_file_paths'] == [f['path'] for f in meta['files']] == sorted(
        n for n in os.listdir(out) if n.endswith('.mcap'))
    assert meta['starting_time']['nanoseconds_since_epoch'] == kept[0][2]
    assert meta['duration']['nanoseconds'] == kept[-1][2] - kept[0][2]
    assert {n: (killed / n).read_bytes() for n in os.listdir(killed)} == before   # untouched


def _states(path):
    reader = bag.BagReader(str(path))
    list(reader.messages())
    return reader.report.files


def test_recover_in_place_replaces_the_files_through_a_temporary_directory(tmp_path, capsys):
    killed, _ = write_killed_bag(tmp_path)
    kept = raw_records(killed)
    assert bag_tool.main(['recover', str(killed), '--in-place']) == 0
    assert f' in {killed}, from ' in capsys.readouterr().out
    assert raw_records(killed) == kept
    assert {f.state for f in _states(killed)} == {'complete'}
    assert [g[2] for g in read_with_rosbags(killed)[0]] == [k[2] for k in kept]
    assert sorted(os.listdir(tmp_path)) == ['b', 'live']             # no temporary left


def test_recover_drops_a_file_killed_before_its_first_chunk(tmp_path, capsys):
    clock = Clock()
    writer = bag.BagWriter(str(tmp_path / 'live' / 'b'), max_file_seconds=1.0, clock=clock)
    writer.add_topic(string_topic())
    for i in range(11):       # log times 0.0 .. 1.0 s: the 11th message opens b_1.mcap
        writer.write('/chatter', cdr_string(f'msg {i}'), log_time_ns=100_000_000 * i)
    killed = killed_copy(tmp_path / 'live' / 'b', tmp_path / 'b')
    writer.close()
    size = os.path.getsize(killed / 'b_1.mcap')
    assert [f.line() for f in _states(killed)] == [
        'b_0.mcap: complete, 10 messages',
        f'b_1.mcap: empty (no complete chunk in {size} bytes: the writer stopped before its '
        'first flush)']
    assert metadata(killed)['relative_file_paths'] == ['b_0.mcap', 'b_1.mcap']
    assert bag_tool.main(['recover', str(killed), '--in-place']) == 0
    capsys.readouterr()
    assert sorted(os.listdir(killed)) == ['b_0.mcap', 'metadata.yaml']
    assert metadata(killed)['relative_file_paths'] == ['b_0.mcap']
    assert kept_texts(killed) == [f'msg {i}' for i in range(10)]


def test_bag_info_reads_the_files_and_says_what_metadata_says(tmp_path, capsys):
    killed, _ = write_killed_bag(tmp_path)
    report = _states(killed)
    assert bag_tool.main(['info', str(killed)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert f'messages:   {sum(f.messages for f in report)}' in lines
    assert [f'  {f.line()}' for f in report] == lines[lines.index('files:') + 1:-1]
    assert lines[-1].startswith('metadata.yaml: ') and 'differs from the files' in lines[-1]
    chatter = [ln.split() for ln in lines if ln.startswith('  /chatter')]
    assert bag_tool.main(['recover', str(killed), '--out', str(tmp_path / 'fixed')]) == 0
    capsys.readouterr()
    counted = read_with_rosbags(tmp_path / 'fixed')[1]['/chatter'].msgcount
    assert chatter == [['/chatter', 'std_msgs/msg/String', str(counted)]]
    assert bag_tool.main(['info', str(tmp_path / 'fixed')]) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert last.startswith('metadata.yaml: ') and 'differs' not in last


def test_bag_info_lists_every_topic_with_its_count_zero_included(tmp_path, capsys):
    """A topic without messages is part of the bag (a deploy bag's /tsr/excitation): info lists
    it as recover does, for the bag and for its one file."""
    with bag.BagWriter(str(tmp_path / 'b')) as writer:
        writer.add_topic(int_topic())
        writer.add_topic(string_topic())
        writer.write('/chatter', cdr_string('only'), log_time_ns=1)
    for path in (tmp_path / 'b', tmp_path / 'b' / 'b_0.mcap'):
        assert bag_tool.main(['info', str(path)]) == 0
        lines = capsys.readouterr().out.splitlines()
        topics = lines[lines.index('topics:') + 1:lines.index('files:')]
        assert [ln.split() for ln in topics] == [['/numbers', 'std_msgs/msg/Int32', '0'],
                                                 ['/chatter', 'std_msgs/msg/String', '1']]
    assert bag_tool.main(['recover', str(tmp_path / 'b')]) == 0
    assert '(/numbers 0, /chatter 1)' in capsys.readouterr().out


def test_recover_of_one_file_says_it_takes_a_bag_directory(tmp_path, capsys):
    killed, _ = write_killed_bag(tmp_path, n=100, kill_at=100)
    out = tmp_path / 'fixed'
    assert bag_tool.main(['recover', str(killed / 'b_0.mcap'), '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f'bag: recover takes a bag directory, not a file: {killed / "b_0.mcap"} '
                   f'(its bag: {killed})\n')
    assert not out.exists()


def test_bag_module_runs_as_a_command(tmp_path):
    killed, _ = write_killed_bag(tmp_path, n=100, kill_at=100)
    run = subprocess.run([sys.executable, '-m', 'tsr_koopman_ctrl.commands.bag', 'info',
                          str(killed)], capture_output=True, text=True)
    assert run.returncode == 0 and run.stdout.startswith(f'bag:        {killed}\n')


@pytest.mark.parametrize('argv', [
    [], ['recover'], ['frobnicate', 'x'], ['recover', 'x', '--out', 'y', '--in-place'],
    ['info', 'x', '--out', 'y']])
def test_bad_arguments_exit_2_with_one_line(argv, capsys):
    assert bag_tool.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith('bag') and err.count('\n') == 1


def test_bad_bags_exit_2_with_one_line(tmp_path, capsys):
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / 'junk_0.mcap').write_bytes(b'not an mcap file at all')
    (tmp_path / 'full').mkdir()
    (tmp_path / 'full' / 'keep').write_text('mine')
    killed, _ = write_killed_bag(tmp_path, n=100, kill_at=100)
    cases = [
        (['recover', str(tmp_path / 'missing')], 'bag: no bag directory at'),
        (['info', str(tmp_path / 'missing')], 'bag: no bag at'),
        (['recover', str(tmp_path / 'junk')], 'bag: no readable messages in'),
        (['info', str(tmp_path / 'junk')], 'bag: no readable messages in'),
        (['recover', str(killed), '--out', str(tmp_path / 'full')], 'bag: '),
    ]
    for argv, start in cases:
        assert bag_tool.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(start) and err.count('\n') == 1, (argv, err)
    assert not (tmp_path / 'junk_recovered').exists()
    assert os.listdir(tmp_path / 'full') == ['keep']


def test_recover_keeps_a_recorded_topic_that_never_had_a_message(tmp_path, capsys):
    """A topic whose publisher never appeared has no channel in the files (it waits for the
    publisher's QoS): after a kill -9 only the recorder's last metadata.yaml names it, and the
    recovered bag lists it with 0 messages, as a clean stop does."""
    writer = bag.BagWriter(str(tmp_path / 'b'), flush_period=0)
    writer.add_topic(string_topic())
    writer.add_topic(int_topic('/silent'), qos_pending=True)
    for i in range(20):
        writer.write('/chatter', cdr_string(f'm{i}'), log_time_ns=10**9 + i)
    writer.flush()
    killed = killed_copy(tmp_path / 'b', tmp_path / 'killed')
    out = tmp_path / 'fixed'
    assert bag_tool.main(['recover', str(killed), '--out', str(out)]) == 0
    assert capsys.readouterr().out.startswith(
        f'kept 20 messages (/chatter 20, /silent 0) in {out}')
    listed = {t['topic_metadata']['name']: (t['topic_metadata']['type'], t['message_count'])
              for t in metadata(out)['topics_with_message_count']}
    assert listed == {'/chatter': ('std_msgs/msg/String', 20),
                      '/silent': ('std_msgs/msg/Int32', 0)}
    got, _ = read_with_rosbags(out)      # still a bag rosbags opens, with every message
    assert [g[3] for g in got] == [f'm{i}' for i in range(20)]
    writer.close()


def test_recover_and_info_are_an_api_the_command_only_prints(tmp_path, capsys):
    """`bag recover` / `bag info` print what `bag.recover` / `bag.info` return (the lab and
    users call those), and nothing else."""
    killed, _ = write_killed_bag(tmp_path)
    result = bag.recover(str(killed), out=str(tmp_path / 'by_api'))
    assert sum(1 for _ in bag.BagReader(result.directory).messages()) == result.messages > 0
    assert bag_tool.main(['recover', str(killed), '--out', str(tmp_path / 'by_command')]) == 0
    assert capsys.readouterr().out == result.line().replace('by_api', 'by_command') + '\n'
    assert bag_tool.main(['info', result.directory]) == 0
    assert capsys.readouterr().out == '\n'.join(bag.info(result.directory)) + '\n'
