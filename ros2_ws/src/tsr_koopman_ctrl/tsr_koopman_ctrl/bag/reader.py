"""The bag reader: a bag directory (or one .mcap file), recovering files a crash left open.

A closed file ends with its summary and footer. A file its writer could not close (SIGKILL)
ends anywhere: the reader walks it record by record and keeps every message of every complete
chunk (its CRC checked) and, from a chunk cut short, the messages of its complete zstd blocks
(a truncated file holds exactly the bytes written, so the prefix of the compressed frame decodes
to a prefix of the chunk, in steps of 128 KiB of messages; no CRC covers that part). Each file
gets a state, and `ReadReport.summary()` one line per file:

    complete            summary and footer present
    truncated           ends without summary: N messages recovered
    empty               0 bytes, or an MCAP file without messages
    not an MCAP file    bad magic
    corrupt             a record inside the file does not decode: the messages before it are kept

`BagReader` refuses (ValueError, one line naming the files) a bag with no readable message.
"""

from dataclasses import dataclass, field
import io
import os
import re
import struct
import zlib

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import get_chunk_data_stream
import yaml
import zstandard

MAGIC = b'\x89MCAP0\r\n'
COMPLETE = 'complete'
TRUNCATED = 'truncated'
EMPTY = 'empty'
NOT_MCAP = 'not an MCAP file'
CORRUPT = 'corrupt'
_RECORD_HEAD = struct.Struct('<BQ')          # opcode, length
_MESSAGE_HEAD = struct.Struct('<HIQQ')       # channel id, sequence, log time, publish time


@dataclass
class BagMessage:
    topic: str
    type: str
    log_time_ns: int        # when the recorder received it (rosbag2 on sim time: the sim clock)
    data: bytes
    publish_time_ns: int = 0    # the publisher's wall clock when the rmw gives it


@dataclass
class FileReport:
    path: str
    state: str = ''
    messages: int = 0              # messages read (recovered, for an incomplete file)
    salvaged: int = 0              # of which from a chunk cut short
    detail: str = ''               # why it is empty or corrupt

    @property
    def complete(self):
        """The file ends with its summary and footer."""
        return self.state == COMPLETE

    def line(self):
        if self.state == COMPLETE:
            return f'{self.path}: complete, {self.messages} messages'
        if self.state == TRUNCATED:
            part = f' ({self.salvaged} from a partly written chunk)' if self.salvaged else ''
            return f'{self.path}: truncated: {self.messages} messages recovered{part}'
        if self.state == CORRUPT:
            return (f'{self.path}: corrupt ({self.detail}): {self.messages} messages recovered '
                    'before it')
        return f'{self.path}: {self.state}' + (f' ({self.detail})' if self.detail else '')


@dataclass
class ReadReport:
    files: list = field(default_factory=list)

    @property
    def messages(self):
        return sum(f.messages for f in self.files)

    @property
    def truncated(self):
        """Names of the files read up to where a crash cut them."""
        return [f.path for f in self.files if f.state == TRUNCATED]

    @property
    def recovered(self):
        """True if messages were recovered from a file left without summary (a crash) or one
        damaged inside."""
        return any(f.state in (TRUNCATED, CORRUPT) and f.messages for f in self.files)

    def summary(self):
        """One line per file: its state and its messages."""
        return '\n'.join(f.line() for f in self.files)


class BagReader:
    """Read a bag directory (or one .mcap file), recovering files a crash left without summary.

    Iterate `messages()` or `decoded()`; `report` then tells what was read, file by file,
    `topics` every topic with a channel in the files read (messages or not), in file order, and
    `type_hash(topic)` the type hash the bag stores for it. Raises ValueError when no file of the
    bag holds a readable message.
    """

    def __init__(self, path):
        if not os.path.exists(path):
            raise FileNotFoundError(f'no bag at {path}')
        self.path = path
        self.files = bag_files(path)
        if not self.files:
            bags = [name for name in sorted(os.listdir(path))
                    if os.path.isdir(os.path.join(path, name))
                    and bag_files(os.path.join(path, name))]
            hint = (f' (a folder of bags: give one, e.g. {os.path.join(path, bags[0])})'
                    if bags else '')
            raise FileNotFoundError(f'no .mcap files in {path}{hint}')
        self.report = ReadReport()
        self.schemas = {}              # type name -> Schema record
        self.topics = {}               # topic name -> type name
        self.channel_hashes = {}       # topic name -> its channel's topic_type_hash
        self._listed_hashes = None
        self._check_readable()

    def type_hash(self, topic):
        """The RIHS01 type hash the bag stores for `topic`: its MCAP channel's
        `topic_type_hash`, else metadata.yaml's `type_description_hash` ('' if neither; read
        the messages first)."""
        if self.channel_hashes.get(topic):
            return self.channel_hashes[topic]
        if self._listed_hashes is None:
            self._listed_hashes = metadata_type_hashes(self.path)
        return self._listed_hashes.get(topic, '')

    def messages(self, topics=None):
        self.report = ReadReport()
        self.topics = {}
        for path in self.files:
            report = FileReport(path=os.path.basename(path))
            self.report.files.append(report)
            schemas, channels = {}, {}
            for record in scan_file(path, report):
                if isinstance(record, Message):
                    topic, type_name = channels[record.channel_id]
                    if topics is None or topic in topics:
                        yield BagMessage(topic, type_name, record.log_time, record.data,
                                         record.publish_time)
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                    self.schemas[record.name] = record
                elif isinstance(record, Channel):
                    schema = schemas.get(record.schema_id)
                    channels[record.id] = (record.topic, schema.name if schema else '')
                    self.topics.setdefault(*channels[record.id])
                    self.channel_hashes[record.topic] = record.metadata.get('topic_type_hash', '')

    def decoded(self, topics=None):
        """Yield (BagMessage, decoded message) using the schema embedded in the bag."""
        from mcap_ros2.decoder import DecoderFactory
        factory, decoders = DecoderFactory(), {}
        for msg in self.messages(topics):
            if msg.type not in decoders:
                decoders[msg.type] = factory.decoder_for('cdr', self.schemas[msg.type])
            yield msg, decoders[msg.type](msg.data)

    def _check_readable(self):
        """Read each file up to its first message; fail early if none has one."""
        probed = []
        for path in self.files:
            report = FileReport(path=os.path.basename(path))
            records = scan_file(path, report)
            try:
                if any(isinstance(r, Message) for r in records):
                    return
            finally:
                records.close()
            probed.append(report.line())
        raise ValueError(f'no readable messages in {self.path}: {"; ".join(probed)}')


def metadata_type_hashes(path):
    """topic -> type_description_hash of a bag directory's metadata.yaml ({} if it has none or
    it cannot be read)."""
    try:
        with open(os.path.join(path, 'metadata.yaml')) as f:
            info = yaml.safe_load(f)['rosbag2_bagfile_information']
        return {t['topic_metadata']['name']: t['topic_metadata'].get('type_description_hash', '')
                for t in info['topics_with_message_count']}
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return {}


def bag_files(path):
    """The .mcap files of a bag directory in split order (or the one file given)."""
    if os.path.isfile(path):
        return [path]
    names = [n for n in os.listdir(path) if n.endswith('.mcap')]
    index = re.compile(r'_(\d+)\.mcap$')
    names.sort(key=lambda n: (int(index.search(n).group(1)) if index.search(n) else -1, n))
    return [os.path.join(path, n) for n in names]


def scan_file(path, report):
    """Yield the Schema, Channel and Message records of one MCAP file in file order, and set
    `report` (state, messages). Bad content ends the scan and is reported, never raised."""
    size = os.path.getsize(path)
    with open(path, 'rb') as stream:
        head = stream.read(len(MAGIC))
        if not head or (len(head) < len(MAGIC) and MAGIC.startswith(head)):
            report.state, report.detail = EMPTY, f'{size} bytes'
            return
        if head != MAGIC:
            report.state = NOT_MCAP
            return
        yield from _scan_records(stream, size, report)
    if report.messages == 0 and report.state in (COMPLETE, TRUNCATED):
        # Never 'recovered' with nothing: a file killed before its first chunk is just empty.
        report.detail = 'no messages' if report.state == COMPLETE else (
            f'no complete chunk in {size} bytes: the writer stopped before its first flush')
        report.state = EMPTY


def _scan_records(stream, size, report):
    offset, in_data = len(MAGIC), True
    while True:
        head = stream.read(_RECORD_HEAD.size)
        if len(head) < _RECORD_HEAD.size:
            report.state = TRUNCATED
            return
        opcode, length = _RECORD_HEAD.unpack(head)
        start = offset + _RECORD_HEAD.size
        if length > size - start:      # the record runs past the end: a crash cut it
            if opcode == Opcode.CHUNK and in_data:
                records = _salvage_chunk(stream.read())
                report.salvaged = sum(isinstance(r, Message) for r in records)
                yield from _counted(records, report)
            report.state = TRUNCATED
            return
        body = stream.read(length)
        try:
            if opcode == Opcode.CHUNK and in_data:
                records = _chunk_records(body)
            elif opcode in _DATA_RECORDS and in_data:
                records = [_record(opcode, body)]
            elif opcode == Opcode.DATA_END:
                in_data, records = False, []
            elif opcode == Opcode.FOOTER:
                complete = stream.read(len(MAGIC)) == MAGIC
                report.state = COMPLETE if complete else TRUNCATED
                return
            else:
                records = []           # indexes, statistics, metadata, attachments
        except Exception as err:       # any decoding failure means damage here
            report.state = CORRUPT
            report.detail = f'{Opcode(opcode).name.lower()} record at byte {offset}: {err}'
            return
        yield from _counted(records, report)
        offset = start + length


def _counted(records, report):
    for record in records:
        if isinstance(record, Message):
            report.messages += 1
        yield record


_DATA_RECORDS = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)


def _record(opcode, body):
    if opcode == Opcode.MESSAGE:
        channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(body)
        return Message(channel_id=channel_id, sequence=sequence, log_time=log_time,
                       publish_time=publish_time, data=body[_MESSAGE_HEAD.size:])
    stream = ReadDataStream(io.BytesIO(body))
    return Schema.read(stream) if opcode == Opcode.SCHEMA else Channel.read(stream)


def _records_in(data, partial=False):
    """Schema, Channel and Message records packed in chunk data; `partial`: data cut short,
    stop at the first incomplete record."""
    records, pos = [], 0
    while pos < len(data):
        if pos + _RECORD_HEAD.size > len(data):
            if partial:
                break
            raise ValueError('chunk data ends inside a record')
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        start = pos + _RECORD_HEAD.size
        if start + length > len(data):
            if partial:
                break
            raise ValueError('chunk data ends inside a record')
        if opcode in _DATA_RECORDS:
            records.append(_record(opcode, data[start:start + length]))
        pos = start + length
    return records


def _chunk_records(body):
    chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
    if chunk.compression == 'zstd':
        data = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == '':
        data = chunk.data
    else:                              # lz4 (other writers), if installed; or mcap's error
        stream, length = get_chunk_data_stream(chunk)
        data = stream.read(length)
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f'chunk holds {len(data)} bytes, not {chunk.uncompressed_size}')
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError('chunk CRC mismatch')
    return _records_in(data)


def _salvage_chunk(body):
    """The complete records at the start of a chunk cut short ([] if none decode)."""
    try:
        compression_length, = struct.unpack_from('<I', body, 28)
        compression = body[32:32 + compression_length].decode()
        data = body[32 + compression_length + 8:]
        if compression == 'zstd':
            data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        elif compression != '':
            return []
        return _records_in(data, partial=True)
    except Exception:                  # a cut can fall anywhere: then nothing to keep
        return []
