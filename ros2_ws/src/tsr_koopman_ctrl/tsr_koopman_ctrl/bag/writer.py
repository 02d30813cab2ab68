"""The bag writer: raw CDR messages into a rosbag2-layout MCAP bag directory.

Layout (what `ros2 bag record -s mcap` of Jazzy writes, so rosbag2, rosbags and Foxglove open
it)::

    <bag>/metadata.yaml          rosbag2_bagfile_information, version 9
    <bag>/<bag>_0.mcap, _1 ...   profile ros2; schemas pkg/msg/Type in ros2msg encoding (full
                                 definition with dependencies); channels in cdr encoding with
                                 offered_qos_profiles and topic_type_hash; a 'rosbag2' metadata
                                 record; zstd-compressed chunks

Messages are stored as the CDR bytes received, never re-serialised.
"""

from dataclasses import dataclass
import os
import time

from mcap.writer import CompressionType, Writer
import yaml

from tsr_koopman_ctrl.bag.definitions import TopicInfo

METADATA_FILE = 'metadata.yaml'
METADATA_VERSION = 9
ROS_DISTRO = 'jazzy'


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
