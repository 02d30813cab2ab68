"""The bag reader: a bag directory (or one .mcap file), recovering files a crash left open.

A file ends with a summary only when it is closed; after a crash the reader streams the file
record by record and keeps every message of every complete chunk, and says so in its report.
"""

from dataclasses import dataclass, field
import os
import re

from mcap.records import Channel, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader


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
