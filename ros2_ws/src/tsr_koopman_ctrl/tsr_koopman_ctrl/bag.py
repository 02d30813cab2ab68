"""rosbag2-layout MCAP bags: the writer and the reader of the project's bag format, ROS-free.

Layout (what `ros2 bag` of Jazzy writes, so rosbag2, rosbags and Foxglove open it)::

    <bag>/metadata.yaml          rosbag2_bagfile_information, version 9
    <bag>/<bag>_0.mcap, _1 ...   profile ros2; schemas pkg/msg/Type in ros2msg encoding (full
                                 definition with dependencies); channels in cdr encoding with
                                 offered_qos_profiles and topic_type_hash; a 'rosbag2' metadata
                                 record; zstd-compressed chunks

Messages are stored as the CDR bytes received, never re-serialised. A file ends with a summary
only when it is closed; after a crash the reader streams the file record by record and keeps
every message of every complete chunk (the chunk size bounds what a SIGKILL loses), and says so.
"""

from dataclasses import dataclass, field
import json
import os
import re
import time

from mcap.records import Channel, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
import numpy as np
from tsr_sim.dynamics import PLANAR_DIM, SPATIAL_DIM
import yaml

METADATA_FILE = 'metadata.yaml'
METADATA_VERSION = 9
ROS_DISTRO = 'jazzy'
DEFINITION_SEPARATOR = '=' * 80
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
               'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'}
# rosbag2 writes an infinite QoS duration as this pair.
_INFINITE_DURATION = {'sec': 2147483647, 'nsec': 4294967295}


@dataclass
class TopicInfo:
    """What a bag stores about one topic."""

    name: str
    type: str                      # pkg/msg/Type
    definition: str                # ros2msg text with dependencies
    type_hash: str = ''            # RIHS01_...
    offered_qos: list = field(default_factory=list)   # list of QoS dicts (see qos_dict)

    @property
    def qos_yaml(self):
        return yaml.safe_dump(self.offered_qos, sort_keys=False) if self.offered_qos else ''


def qos_dict(history, depth, reliability, durability, liveliness, deadline_ns, lifespan_ns,
             lease_ns, avoid_ros_namespace_conventions=False):
    """One offered QoS profile in rosbag2's YAML form (enum values as integers)."""
    def duration(ns):
        if ns is None or ns <= 0 or ns >= 2 ** 63 - 1:
            return dict(_INFINITE_DURATION) if ns else {'sec': 0, 'nsec': 0}
        return {'sec': int(ns // 10 ** 9), 'nsec': int(ns % 10 ** 9)}
    return {'history': int(history), 'depth': int(depth), 'reliability': int(reliability),
            'durability': int(durability), 'deadline': duration(deadline_ns),
            'lifespan': duration(lifespan_ns), 'liveliness': int(liveliness),
            'liveliness_lease_duration': duration(lease_ns),
            'avoid_ros_namespace_conventions': bool(avoid_ros_namespace_conventions)}


# ---------------------------------------------------------------------------------------------
# Message definitions and type hashes from an installed ROS prefix (share/<pkg>/msg/<T>.msg/.json)

def _interface_file(type_name, suffix):
    from ament_index_python.packages import get_package_share_directory
    package, kind, name = type_name.split('/')
    return os.path.join(get_package_share_directory(package), kind, name + suffix)


def message_definition(type_name, read_msg=None):
    """Full ros2msg definition of `pkg/msg/Type`: its .msg text, then every dependency after a
    separator line and 'MSG: pkg/msg/Dep', depth first, each once (what rosbag2 stores)."""
    read_msg = read_msg or (lambda t: open(_interface_file(t, '.msg')).read())
    parts, seen = [], set()

    def visit(name, is_root):
        if name in seen:
            return
        seen.add(name)
        text = read_msg(name)
        parts.append(text if is_root else f'{DEFINITION_SEPARATOR}\nMSG: {name}\n{text}')
        for dep in _field_types(text, name.split('/')[0]):
            visit(dep, False)

    visit(type_name, True)
    return '\n'.join(part.rstrip('\n') for part in parts) + '\n'


def _field_types(text, package):
    """Non-primitive field types of a .msg text, as pkg/msg/Type, in order."""
    for line in text.splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        type_token, rest = line.split(None, 1)
        if '=' in rest.split()[0]:        # a constant: TYPE NAME=VALUE
            continue
        base = re.sub(r'\[.*\]$', '', type_token).split('<=')[0]
        if base in _PRIMITIVES:
            continue
        if base == 'Header':
            yield 'std_msgs/msg/Header'
        elif '/' in base:
            pkg, name = base.split('/')[0], base.split('/')[-1]
            yield f'{pkg}/msg/{name}'
        else:
            yield f'{package}/msg/{base}'


def type_hash(type_name):
    """The RIHS01 type description hash from the installed <Type>.json ('' if not found)."""
    try:
        with open(_interface_file(type_name, '.json')) as f:
            hashes = json.load(f)['type_hashes']
    except (OSError, KeyError, ValueError):
        return ''
    return next((h['hash_string'] for h in hashes if h['type_name'] == type_name), '')


# ---------------------------------------------------------------------------------------------
# Writer

@dataclass
class _FileStats:
    path: str
    start_ns: int = 0
    end_ns: int = 0
    count: int = 0


class BagWriter:
    """Write raw CDR messages into a rosbag2-layout MCAP bag directory.

    A new file starts when the current one exceeds `max_file_bytes` or spans more than
    `max_file_seconds` of log time (0: no limit). metadata.yaml is rewritten at every split and
    at close, so the files closed before a crash are listed.
    """

    def __init__(self, directory, max_file_bytes=0, max_file_seconds=0.0,
                 chunk_size=1 << 20):
        if os.path.exists(directory) and os.listdir(directory):
            raise FileExistsError(f'bag directory {directory} exists and is not empty')
        os.makedirs(directory, exist_ok=True)
        self.directory = directory
        self.name = os.path.basename(os.path.normpath(directory))
        self.max_file_bytes = max_file_bytes
        self.max_file_ns = int(max_file_seconds * 1e9)
        self.chunk_size = chunk_size
        self.topics = {}               # name -> TopicInfo
        self.topic_counts = {}
        self.files = []
        self._stream = self._writer = None
        self._channel_ids = {}
        self._open_file()

    def add_topic(self, info: TopicInfo):
        if info.name in self.topics:
            raise ValueError(f'topic {info.name} already added')
        self.topics[info.name] = info
        self.topic_counts[info.name] = 0
        self._register(info)

    def write(self, topic, cdr_bytes, log_time_ns=None):
        if self._writer is None:
            raise ValueError(f'bag {self.directory} is closed')
        log_time_ns = time.time_ns() if log_time_ns is None else int(log_time_ns)
        current = self.files[-1]
        if current.count and self._file_full(current, log_time_ns):
            self._split()
            current = self.files[-1]
        self._writer.add_message(self._channel_ids[topic], log_time_ns, bytes(cdr_bytes),
                                 log_time_ns, sequence=current.count)
        current.start_ns = log_time_ns if current.count == 0 else current.start_ns
        current.end_ns = log_time_ns
        current.count += 1
        self.topic_counts[topic] += 1

    def close(self):
        if self._writer is None:
            return
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

    def _file_full(self, current, log_time_ns):
        too_big = self.max_file_bytes and self._stream.tell() >= self.max_file_bytes
        too_long = self.max_file_ns and log_time_ns - current.start_ns >= self.max_file_ns
        return bool(too_big or too_long)

    def _open_file(self):
        path = os.path.join(self.directory, f'{self.name}_{len(self.files)}.mcap')
        self._stream = open(path, 'wb')
        self._writer = Writer(self._stream, chunk_size=self.chunk_size,
                              compression=CompressionType.ZSTD)
        self._writer.start(profile='ros2', library='tsr_koopman_ctrl')
        self._channel_ids = {}
        self.files.append(_FileStats(path=os.path.basename(path)))
        for info in self.topics.values():
            self._register(info)

    def _register(self, info):
        schema_id = self._writer.register_schema(
            name=info.type, encoding='ros2msg', data=info.definition.encode())
        self._channel_ids[info.name] = self._writer.register_channel(
            topic=info.name, message_encoding='cdr', schema_id=schema_id,
            metadata={'offered_qos_profiles': info.qos_yaml, 'topic_type_hash': info.type_hash})

    def _finish_file(self):
        self._writer.add_metadata('rosbag2', {
            'ROS_DISTRO': ROS_DISTRO,
            'serialized_metadata': yaml.safe_dump(self._metadata(), sort_keys=False)})
        self._writer.finish()
        self._stream.close()

    def _split(self):
        self._finish_file()
        self._open_file()
        self._write_metadata()

    def _metadata(self):
        def stamp(ns):
            return {'nanoseconds_since_epoch': int(ns)}
        used = [f for f in self.files if f.count]
        start = min((f.start_ns for f in used), default=0)
        end = max((f.end_ns for f in used), default=0)
        return {'rosbag2_bagfile_information': {
            'version': METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': end - start},
            'starting_time': stamp(start),
            'message_count': self.message_count,
            'topics_with_message_count': [
                {'topic_metadata': {'name': info.name, 'type': info.type,
                                    'serialization_format': 'cdr',
                                    'offered_qos_profiles': info.qos_yaml,
                                    'type_description_hash': info.type_hash},
                 'message_count': self.topic_counts[info.name]}
                for info in self.topics.values()],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [f.path for f in self.files],
            'files': [{'path': f.path, 'starting_time': stamp(f.start_ns),
                       'duration': {'nanoseconds': f.end_ns - f.start_ns},
                       'message_count': f.count} for f in self.files],
            'custom_data': {},
            'ros_distro': ROS_DISTRO}}

    def _write_metadata(self):
        tmp = os.path.join(self.directory, METADATA_FILE + '.tmp')
        with open(tmp, 'w') as f:
            yaml.safe_dump(self._metadata(), f, sort_keys=False)
        os.replace(tmp, os.path.join(self.directory, METADATA_FILE))


# ---------------------------------------------------------------------------------------------
# Reader

@dataclass
class BagMessage:
    topic: str
    type: str
    log_time_ns: int
    data: bytes


@dataclass
class FileReport:
    path: str
    messages: int = 0
    complete: bool = False         # the file ends with its summary and footer
    error: str = ''                # why reading stopped early, if it did


@dataclass
class ReadReport:
    files: list = field(default_factory=list)

    @property
    def messages(self):
        return sum(f.messages for f in self.files)

    @property
    def recovered(self):
        """True if any file was incomplete (a crash) and was read up to its last good chunk."""
        return any(not f.complete for f in self.files)

    def summary(self):
        lines = [f'{self.messages} messages in {len(self.files)} file(s)']
        for f in self.files:
            state = 'complete' if f.complete else f'RECOVERED (incomplete: {f.error})'
            lines.append(f'  {f.path}: {f.messages} messages, {state}')
        return '\n'.join(lines)


class BagReader:
    """Read a bag directory (or one .mcap file), recovering files a crash left without summary.

    Iterate `messages()`; `report` tells what was read and what was recovered.
    """

    def __init__(self, path):
        if not os.path.exists(path):
            raise FileNotFoundError(f'no bag at {path}')
        self.path = path
        self.files = _bag_files(path)
        if not self.files:
            raise FileNotFoundError(f'no .mcap files in {path}')
        self.report = ReadReport()
        self.schemas = {}              # type name -> Schema record

    def messages(self, topics=None):
        self.report = ReadReport()
        for path in self.files:
            yield from self._read_file(path, topics)

    def decoded(self, topics=None):
        """Yield (BagMessage, decoded message) using the schema embedded in the bag."""
        from mcap_ros2.decoder import DecoderFactory
        factory, decoders = DecoderFactory(), {}
        for msg in self.messages(topics):
            if msg.type not in decoders:
                decoders[msg.type] = factory.decoder_for('cdr', self.schemas[msg.type])
            yield msg, decoders[msg.type](msg.data)

    def _read_file(self, path, topics):
        report = FileReport(path=os.path.basename(path))
        self.report.files.append(report)
        schemas, channels = {}, {}
        with open(path, 'rb') as stream:
            try:
                for record in StreamReader(stream, validate_crcs=True).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                        self.schemas[record.name] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Message):
                        channel = channels[record.channel_id]
                        report.messages += 1
                        if topics is None or channel.topic in topics:
                            yield BagMessage(channel.topic, schemas[channel.schema_id].name,
                                             record.log_time, record.data)
                    elif isinstance(record, (DataEnd, Footer)):
                        report.complete = True
            except Exception as err:  # a crashed file can end anywhere, in any record
                report.error = f'{type(err).__name__}: {err}'
            if not report.complete and not report.error:
                report.error = 'file ends without summary (writer did not close it)'


def _bag_files(path):
    if os.path.isfile(path):
        return [path]
    names = [n for n in os.listdir(path) if n.endswith('.mcap')]
    index = re.compile(r'_(\d+)\.mcap$')
    names.sort(key=lambda n: (int(index.search(n).group(1)) if index.search(n) else -1, n))
    return [os.path.join(path, n) for n in names]


# ---------------------------------------------------------------------------------------------
# The deployment loop's topics (tsr_msgs) as arrays

STATE_TOPIC = '/tsr/state'
TENSION_TOPIC = '/tsr/tension_cmd'


def read_loop(path, scale):
    """Read the loop of a bag: {'step', 'tau', 'x' (dimensionless), 'u' (per step, nan where
    no command), 'report'}. Republished states count once; the first command per step is the
    one a lockstep simulator applies."""
    reader = BagReader(path)
    states, tensions = {}, {}
    for msg, decoded in reader.decoded({STATE_TOPIC, TENSION_TOPIC}):
        if msg.topic == STATE_TOPIC:
            si = [decoded.theta, decoded.theta_rate, decoded.length, decoded.length_rate]
            if decoded.has_out_of_plane:
                si += [decoded.beta, decoded.beta_rate]
            stamp = decoded.header.stamp.sec + decoded.header.stamp.nanosec * 1e-9
            states[decoded.step] = (stamp, si)
        else:
            tensions.setdefault(decoded.step, decoded.tension)
    if not states:
        raise ValueError(f'bag {path} has no {STATE_TOPIC} messages')
    steps = np.array(sorted(states))
    dim = SPATIAL_DIM if any(len(states[s][1]) == SPATIAL_DIM for s in steps) else PLANAR_DIM
    x = scale.state_from_si(np.array([states[s][1][:dim] for s in steps]))
    tau = np.array([scale.seconds_to_tau(states[s][0]) for s in steps])
    u = np.array([scale.tension_to_u(tensions.get(s, np.nan)) for s in steps])
    return {'step': steps, 'tau': tau, 'x': x, 'u': u, 'report': reader.report}
