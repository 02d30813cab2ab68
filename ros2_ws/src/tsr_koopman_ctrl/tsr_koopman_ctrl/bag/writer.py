"""The bag writer: raw CDR messages into a rosbag2-layout MCAP bag directory.

Layout (what `ros2 bag record -s mcap` of Jazzy writes, so rosbag2, rosbags and Foxglove open
it)::

    <bag>/metadata.yaml          rosbag2_bagfile_information, version 9
    <bag>/<bag>_0.mcap, _1 ...   profile ros2; schemas pkg/msg/Type in ros2msg encoding (full
                                 definition with dependencies); channels in cdr encoding with
                                 offered_qos_profiles and topic_type_hash; a 'rosbag2' metadata
                                 record; zstd-compressed chunks

Messages are stored as the CDR bytes received, never re-serialised, with the times rosbag2
0.26 (Jazzy) stores (`write_received`): the log time is when the message was received (the
rmw's received_timestamp, on sim time too, where rosbag2 would log the sim clock: see
`write_received`), the publish time when it was sent (source_timestamp), and the sequence
number is 0, which rosbag2 0.26 writes for every
message (ros2/rosbag2 tag 0.26.5: rosbag2_storage_mcap/src/mcap_storage.cpp `write_lock_free`;
rosbag2_transport/src/rosbag2_transport/recorder.cpp `create_subscription`).

Crash safety. Messages wait in memory until their chunk is written, so the writer bounds that
wait in bytes and in time: a chunk is written when it reaches `chunk_size` bytes, and the chunk
in progress is closed and the file flushed to the OS once its oldest message is `flush_period`
seconds old (checked in `write()` and in `flush_if_due()`, which a recorder calls from a timer
so that an idle stream is flushed too). After a SIGKILL the OS still holds every byte flushed, so
at most the last `flush_period` of messages (and at most one chunk) is lost; `BagReader` reads
the rest and `python -m tsr_koopman_ctrl.commands.bag recover` makes a complete bag of it. There is
no fsync: a power loss can lose what the OS had not written to the disk yet.

A topic's offered QoS can be learnt after it is added (a recorder subscribes before any
publisher is known, so that nothing is missed): `add_topic(info, qos_pending=True)` lists it in
metadata.yaml at once but holds back its MCAP channel, which cannot change once written, until
`set_offered_qos`, its first message or the close, whichever comes first.

metadata.yaml is written when the first file opens and rewritten (atomically) at every time
flush, split, new topic, learnt QoS and at close, so a killed bag always lists its files and
topics. Its message counts are those of the last rewrite: after a kill they can lag what the
files hold (chunks written by size since then); the files, as read, are the truth.
"""

from dataclasses import dataclass
import datetime
import inspect
import os
import secrets
import time

from mcap.writer import CompressionType, Writer
import yaml

from tsr_koopman_ctrl.bag.definitions import TopicInfo

METADATA_FILE = 'metadata.yaml'
METADATA_VERSION = 9
ROS_DISTRO = 'jazzy'
LIBRARY = 'tsr_koopman_ctrl'


def new_bag_name(directory, prefix):
    """'<prefix>_<UTC time to the microsecond>_<6 random hex digits>', drawn again while
    <directory>/<name> exists: bags started in the same second, by one process or several, get
    distinct names, and an existing directory is never reused."""
    while True:
        now = datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%d_%H%M%S_%f')
        name = f'{prefix}_{now}_{secrets.token_hex(3)}'
        if not os.path.exists(os.path.join(directory, name)):
            return name


@dataclass
class FileStats:
    """What metadata.yaml says about one file of a bag."""

    path: str                      # relative to the bag directory
    start_ns: int = 0
    end_ns: int = 0
    count: int = 0

    def add(self, log_time_ns):
        self.start_ns = log_time_ns if self.count == 0 else min(self.start_ns, log_time_ns)
        self.end_ns = log_time_ns if self.count == 0 else max(self.end_ns, log_time_ns)
        self.count += 1


@dataclass
class TopicStats:
    """What metadata.yaml says about one topic (qos and hash as the channel metadata has them)."""

    name: str
    type: str
    qos_yaml: str = ''
    type_hash: str = ''
    count: int = 0


class _CountingFile:
    """A file opened for writing that counts what was written: `tell()` without a system
    call, and `written` shows when the MCAP writer has written a chunk."""

    def __init__(self, path):
        self._file = open(path, 'wb')
        self.written = 0

    def write(self, data):
        self.written += len(data)
        return self._file.write(data)

    def tell(self):
        return self.written

    def flush(self):
        self._file.flush()

    def close(self):
        self._file.close()


class ReceivedCallback:
    """A subscription callback that gets rclpy's MessageInfo on every executor: calls
    `function(msg, info)`; give it to `create_subscription` and feed `BagWriter.write_received`.

    rclpy hands the info to a callback whose signature takes two arguments, so this one says
    it does (`__signature__`). The Jazzy EventsExecutor (rclpy 7.1.6, events_executor.cpp
    `HandleSubscriptionReady`: `callback(msg_info)`) then passes the (msg, info) pair as one
    argument where the other executors pass two; both are taken."""

    __signature__ = inspect.Signature(
        [inspect.Parameter(name, inspect.Parameter.POSITIONAL_ONLY) for name in ('msg', 'info')])

    def __init__(self, function):
        self.function = function

    def __call__(self, *args):
        msg, info = args if len(args) == 2 else args[0]
        return self.function(msg, info)


def open_mcap(path, chunk_size=1 << 20):
    """A new MCAP file with the rosbag2 profile; returns (stream, writer)."""
    stream = _CountingFile(path)
    writer = Writer(stream, chunk_size=chunk_size, compression=CompressionType.ZSTD)
    writer.start(profile='ros2', library=LIBRARY)
    return stream, writer


def finish_mcap(stream, writer, metadata):
    """Close an MCAP file: the 'rosbag2' metadata record rosbag2 writes, summary, footer.

    The record holds the bag's metadata (`bag_metadata`) without its metadata.yaml wrapper, as
    rosbag2 0.26 writes and reads it: `MCAPStorage::update_metadata` and `read_metadata` in
    rosbag2_storage_mcap/src/mcap_storage.cpp (tag 0.26.5), one 'serialized_metadata' key."""
    information = metadata['rosbag2_bagfile_information']
    writer.add_metadata('rosbag2', {
        'serialized_metadata': yaml.safe_dump(information, sort_keys=False)})
    writer.finish()
    stream.close()


def bag_metadata(topics, files):
    """rosbag2's metadata.yaml content for `topics` (TopicStats) and `files` (FileStats)."""
    def stamp(ns):
        return {'nanoseconds_since_epoch': int(ns)}
    used = [f for f in files if f.count]
    start = min((f.start_ns for f in used), default=0)
    end = max((f.end_ns for f in used), default=0)
    return {'rosbag2_bagfile_information': {
        'version': METADATA_VERSION,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': end - start},
        'starting_time': stamp(start),
        'message_count': sum(t.count for t in topics),
        'topics_with_message_count': [
            {'topic_metadata': {'name': t.name, 'type': t.type,
                                'serialization_format': 'cdr',
                                # version 9: the profiles as YAML, not the channel's string
                                'offered_qos_profiles': yaml.safe_load(t.qos_yaml) or [],
                                'type_description_hash': t.type_hash},
             'message_count': t.count}
            for t in topics],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.path for f in files],
        'files': [{'path': f.path, 'starting_time': stamp(f.start_ns),
                   'duration': {'nanoseconds': f.end_ns - f.start_ns},
                   'message_count': f.count} for f in files],
        'custom_data': {},
        'ros_distro': ROS_DISTRO}}


def write_metadata(directory, metadata):
    """Replace <directory>/metadata.yaml atomically: a reader never sees half a file."""
    tmp = os.path.join(directory, METADATA_FILE + '.tmp')
    with open(tmp, 'w') as f:
        yaml.safe_dump(metadata, f, sort_keys=False)
    os.replace(tmp, os.path.join(directory, METADATA_FILE))


class BagWriter:
    """Write raw CDR messages into a rosbag2-layout MCAP bag directory.

    A new file starts when the current one exceeds `max_file_bytes` or spans more than
    `max_file_seconds` of log time (0: no limit). The chunk in progress is written and the file
    flushed once its oldest message is `flush_period` seconds old (0: only when the chunk
    reaches `chunk_size` bytes); call `flush_if_due()` periodically so an idle stream is
    flushed too. `clock` (seconds, monotonic) is what `flush_period` is measured on. Not
    thread-safe: write, flush and close from one thread (a node's executor).
    """

    def __init__(self, directory, max_file_bytes=0, max_file_seconds=0.0,
                 chunk_size=1 << 20, flush_period=1.0, clock=time.monotonic):
        if flush_period < 0:
            raise ValueError(f'flush_period must be >= 0, not {flush_period}')
        if os.path.exists(directory) and os.listdir(directory):
            raise FileExistsError(f'bag directory {directory} exists and is not empty')
        os.makedirs(directory, exist_ok=True)
        self.directory = directory
        self.name = os.path.basename(os.path.normpath(directory))
        self.max_file_bytes = max_file_bytes
        self.max_file_ns = int(max_file_seconds * 1e9)
        self.chunk_size = chunk_size
        self.flush_period = float(flush_period)
        self.clock = clock
        self.topics = {}               # name -> TopicInfo
        self.topic_counts = {}
        self.files = []
        self._stream = self._writer = None
        self._channel_ids = {}
        self.qos_pending = set()       # topics whose channel waits for their offered QoS
        self._pending_since = None     # clock time of the oldest message not yet on disk
        #: `clock` time of the last write to the OS (a chunk written, a flush), or None.
        self.last_flush_wall = None
        self.last_log_time_ns = 0      # of the last message received: log times never go back
        self._closed_bytes = 0         # bytes of the files finished before the current one
        self._open_file()

    def add_topic(self, info: TopicInfo, qos_pending=False):
        """Add a topic; `qos_pending`: its offered QoS is not known yet, so its channel is
        written at `set_offered_qos`, its first message or the close, whichever comes first."""
        if info.name in self.topics:
            raise ValueError(f'topic {info.name} already added')
        self.topics[info.name] = info
        self.topic_counts[info.name] = 0
        if qos_pending:
            self.qos_pending.add(info.name)
        else:
            self._register(info)
        self._write_metadata()

    def set_offered_qos(self, topic, offered_qos):
        """The offered QoS (list of `definitions.qos_dict`) of a topic added with
        `qos_pending`; writes its channel. ValueError once its channel is written."""
        if topic not in self.qos_pending:
            raise ValueError(f'topic {topic} is not waiting for its QoS')
        self.topics[topic].offered_qos = list(offered_qos)
        self._register_pending(topic)
        self._write_metadata()

    def write_received(self, topic, cdr_bytes, message_info):
        """Write a message a subscription took, with rclpy's MessageInfo (the callback's second
        argument): log time the received_timestamp (now if the rmw gives none), never earlier
        than the message written before it, so that stock tools (`ros2 bag play`, Foxglove)
        play the bag in the order it was received; publish time the source_timestamp (the log
        time if none). On sim time too: rosbag2 logs the node's sim clock there, which goes
        back at a reset and mixes two loops' clocks on one domain; the messages' headers carry
        sim time."""
        received = int(message_info.get('received_timestamp') or 0)
        log_time_ns = max(received if received > 0 else time.time_ns(), self.last_log_time_ns)
        self.last_log_time_ns = log_time_ns
        sent = int(message_info.get('source_timestamp') or 0)
        self.write(topic, cdr_bytes, log_time_ns, sent if sent > 0 else log_time_ns)

    def write(self, topic, cdr_bytes, log_time_ns=None, publish_time_ns=None):
        """Write one message; the log time defaults to now, the publish time to the log time.
        The sequence number is 0, as rosbag2 0.26 writes it."""
        if self._writer is None:
            raise ValueError(f'bag {self.directory} is closed')
        log_time_ns = time.time_ns() if log_time_ns is None else int(log_time_ns)
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        current = self.files[-1]
        if current.count and self._file_full(current, log_time_ns):
            self._split()
            current = self.files[-1]
        if topic in self.qos_pending:
            self._register_pending(topic)      # QoS still unknown: the message must not wait
        stream = self._stream
        written = stream.written
        self._writer.add_message(self._channel_ids[topic], log_time_ns, bytes(cdr_bytes),
                                 publish_time_ns, sequence=0)
        current.add(log_time_ns)
        self.topic_counts[topic] += 1
        if stream.written != written:
            # The chunk filled up and was written (this message with it): hand it to the OS
            # now, not when Python's buffer happens to fill.
            stream.flush()
            self._pending_since = None
            self.last_flush_wall = self.clock()
        elif self._pending_since is None:
            self._pending_since = self.clock()
        elif self.flush_period:
            self.flush_if_due()

    def flush_if_due(self, now=None):
        """Flush if the oldest message in memory is `flush_period` old; cheap otherwise.
        Returns True if it flushed."""
        if self._pending_since is None or not self.flush_period or self._writer is None:
            return False
        now = self.clock() if now is None else now
        if now - self._pending_since < self.flush_period:
            return False
        self.flush()
        return True

    def flush(self):
        """Write the chunk in progress, flush the file to the OS, rewrite metadata.yaml."""
        if self._writer is None:
            return
        self._writer.flush()
        self._pending_since = None
        self.last_flush_wall = self.clock()
        self._write_metadata()

    def close(self):
        if self._writer is None:
            return
        for topic in list(self.qos_pending):   # every topic gets its channel, messages or not
            self._register_pending(topic)
        self._finish_file()
        self._write_metadata()
        self._writer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def message_count(self):
        return sum(self.topic_counts.values())

    @property
    def bytes_written(self):
        """Bytes handed to the files so far (what a crash would leave, at most)."""
        current = self._stream.written if self._writer is not None else 0
        return self._closed_bytes + current

    def _file_full(self, current, log_time_ns):
        too_big = self.max_file_bytes and self._stream.written >= self.max_file_bytes
        too_long = self.max_file_ns and log_time_ns - current.start_ns >= self.max_file_ns
        return bool(too_big or too_long)

    def _open_file(self):
        path = os.path.join(self.directory, f'{self.name}_{len(self.files)}.mcap')
        self._stream, self._writer = open_mcap(path, self.chunk_size)
        self._stream.flush()           # the magic and header: the file is an MCAP from now on
        self._channel_ids = {}
        self.files.append(FileStats(path=os.path.basename(path)))
        for info in self.topics.values():
            if info.name not in self.qos_pending:
                self._register(info)
        self._write_metadata()

    def _register_pending(self, topic):
        self.qos_pending.discard(topic)
        self._register(self.topics[topic])

    def _register(self, info):
        schema_id = self._writer.register_schema(
            name=info.type, encoding='ros2msg', data=info.definition.encode())
        self._channel_ids[info.name] = self._writer.register_channel(
            topic=info.name, message_encoding='cdr', schema_id=schema_id,
            metadata={'offered_qos_profiles': info.qos_yaml, 'topic_type_hash': info.type_hash})

    def _finish_file(self):
        finish_mcap(self._stream, self._writer, self._metadata())
        self._closed_bytes += self._stream.written
        self._pending_since = None

    def _split(self):
        self._finish_file()
        self._open_file()

    def _metadata(self):
        topics = [TopicStats(info.name, info.type, info.qos_yaml, info.type_hash,
                             self.topic_counts[info.name]) for info in self.topics.values()]
        return bag_metadata(topics, self.files)

    def _write_metadata(self):
        write_metadata(self.directory, self._metadata())
