"""A bag's files as a whole, ROS-free: what they hold (`info`), the runs of the loop they hold
(`runs`), and a complete bag from one a crash left open (`recover`). The `bag` command
(commands/bag.py) prints what these return; the lab and your tools call them alike.

    from tsr_koopman_ctrl.bag.files import info, recover, runs
    print('\n'.join(info('bags/deploy_...')))
    print(recover('bags/killed', out='bags/fixed').line())

`info` (a bag directory or one .mcap file) reads every file (not only metadata.yaml, which lags
the files of a killed bag): files with their state, every topic with its type and count (0
included), start and duration, and what metadata.yaml says. `runs` reads the loop as
`read_runs` does and describes its units, sample period and command matching, then one line per
run of the simulator. `recover` (like `ros2 bag reindex` / `mcap recover`) takes a bag
directory (its output is a bag, which one file of a split bag is not), reads each file as
`BagReader` does (every complete chunk, and of a chunk cut short its complete zstd blocks; what
was still in the writer's memory never reached the file) and writes it anew, with the same name,
complete and indexed: the same schemas, channels (QoS and type hash in their metadata), log and
publish times, sequence numbers and order, plus a metadata.yaml with the true counts (and, from
the bag's own metadata.yaml, the topics recorded that never had a message, so no channel).
Output: `<BAG>_recovered` next to the bag, or `out`; `in_place` writes to a temporary directory
next to the bag first, then replaces the bag's files one by one (os.replace) and metadata.yaml
last, removes files that hold no message, and refuses a bag with a corrupt or non-MCAP file
(their unreadable bytes would be lost). Errors: ValueError, OSError or RuntimeError, one line.
"""

import datetime
import os
import shutil
import tempfile

from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
import numpy as np
import yaml

from tsr_koopman_ctrl.bag.reader import (BagReader, bag_files, CORRUPT, EMPTY, FileReport,
                                         NOT_MCAP, scan_file)
from tsr_koopman_ctrl.bag.tsr_loop import H_SOURCES, read_runs, UNITS_SOURCES
from tsr_koopman_ctrl.bag.writer import (bag_metadata, FileStats, finish_mcap, METADATA_FILE,
                                         open_mcap, TopicStats, write_metadata)


class Recovered:
    """What `recover` wrote: per-file reports of the source, files and topics written."""

    def __init__(self, directory):
        self.directory = directory
        self.reports = []              # FileReport per source file
        self.files = []                # FileStats per file written
        self.topics = {}               # name -> TopicStats

    @property
    def messages(self):
        return sum(t.count for t in self.topics.values())

    def line(self):
        topics = ', '.join(f'{t.name} {t.count}' for t in self.topics.values())
        sources = '; '.join(r.line() for r in self.reports)
        return (f'kept {self.messages} messages ({topics}) in {self.directory}, from '
                f'{sources}')


def recover(bag, out=None, in_place=False):
    """Write the readable messages of `bag` as a complete bag (see the module docstring)."""
    bag = os.path.normpath(bag)
    if os.path.isfile(bag):
        # As `ros2 bag reindex`: the output is a bag (its metadata.yaml lists all its files),
        # which one file of a split bag is not.
        raise ValueError(f'recover takes a bag directory, not a file: {bag} (its bag: '
                         f'{os.path.dirname(bag) or "."})')
    if not os.path.isdir(bag):
        raise FileNotFoundError(f'no bag directory at {bag}')
    BagReader(bag)                     # one line if there is nothing to recover
    if in_place:
        work = tempfile.mkdtemp(prefix=f'.{os.path.basename(bag)}.recover-',
                                dir=os.path.dirname(os.path.abspath(bag)))
        try:
            result = _rewrite(bag, work)
            unreadable = [r.line() for r in result.reports if r.state in (CORRUPT, NOT_MCAP)]
            if unreadable:
                raise ValueError(f'{unreadable[0]}: --in-place would drop its unreadable bytes; '
                                 'recover with --out')
            for stats in result.files:
                os.replace(os.path.join(work, stats.path), os.path.join(bag, stats.path))
            for report in result.reports:
                if report.state == EMPTY:
                    os.remove(os.path.join(bag, report.path))
            os.replace(os.path.join(work, METADATA_FILE), os.path.join(bag, METADATA_FILE))
        finally:
            shutil.rmtree(work, ignore_errors=True)
        result.directory = bag
        return result
    out = os.path.normpath(out or bag + '_recovered')
    if os.path.exists(out) and (not os.path.isdir(out) or os.listdir(out)):
        raise FileExistsError(f'{out} exists and is not an empty directory')
    created = not os.path.exists(out)
    os.makedirs(out, exist_ok=True)
    try:
        return _rewrite(bag, out)
    except BaseException:
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise


def _rewrite(bag, target):
    result = Recovered(target)
    for path in bag_files(bag):
        report = FileReport(path=os.path.basename(path))
        result.reports.append(report)
        stats = FileStats(path=report.path)
        out_path = os.path.join(target, report.path)
        stream, writer = open_mcap(out_path)
        schemas, schema_ids, channel_ids, channel_topics = {}, {}, {}, {}
        for record in scan_file(path, report):
            if isinstance(record, Message):
                writer.add_message(channel_ids[record.channel_id], record.log_time,
                                   record.data, record.publish_time, record.sequence)
                stats.add(record.log_time)
                result.topics[channel_topics[record.channel_id]].count += 1
            elif isinstance(record, Schema) and record.id not in schema_ids:
                schemas[record.id] = record
                schema_ids[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data)
            elif isinstance(record, Channel) and record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0),
                    dict(record.metadata))
                channel_topics[record.id] = record.topic
                schema = schemas.get(record.schema_id)
                result.topics.setdefault(record.topic, TopicStats(
                    record.topic, schema.name if schema else '',
                    record.metadata.get('offered_qos_profiles', ''),
                    record.metadata.get('topic_type_hash', '')))
        if not stats.count:            # nothing to keep: no file
            stream.close()
            os.remove(out_path)
            continue
        result.files.append(stats)
        finish_mcap(stream, writer, bag_metadata(list(result.topics.values()), result.files))
        _check_written(out_path, stats.count)
    for topic in _listed_topics(bag):  # recorded but never published: no channel in the files
        result.topics.setdefault(topic.name, topic)
    write_metadata(target, bag_metadata(list(result.topics.values()), result.files))
    return result


def _listed_topics(bag):
    """The topics the bag's own metadata.yaml lists, with 0 messages (TopicStats; [] if it
    cannot be read). A recorder writes it at every flush with every topic it records; a topic
    whose publisher never appeared has no channel in the files (its channel waits for the
    QoS), so after a kill -9 this is the only record of it."""
    try:
        info = _bag_information(bag)
        listed = [entry['topic_metadata'] for entry in info['topics_with_message_count']]
        return [TopicStats(t['name'], t['type'],
                           yaml.safe_dump(t['offered_qos_profiles'], sort_keys=False)
                           if t.get('offered_qos_profiles') else '',
                           t.get('type_description_hash', '')) for t in listed]
    except METADATA_ERRORS:
        return []


#: What reading a metadata.yaml that is missing, not YAML or not rosbag2's may raise.
METADATA_ERRORS = (OSError, yaml.YAMLError, KeyError, TypeError)


def _bag_information(bag):
    """The rosbag2_bagfile_information mapping of the bag's metadata.yaml (METADATA_ERRORS)."""
    with open(os.path.join(bag, METADATA_FILE)) as f:
        return yaml.safe_load(f)['rosbag2_bagfile_information']


def _check_written(path, count):
    """The file just written ends with a summary that counts what was written into it."""
    with open(path, 'rb') as f:
        summary = make_reader(f).get_summary()
    said = summary.statistics.message_count if summary and summary.statistics else None
    if said != count:
        raise RuntimeError(f'{path}: wrote {count} messages, its summary says {said}')


def runs(bag, namespace=None, **reading):
    """Lines describing the loop of `bag` as `read_runs(bag, namespace=..., **reading)` reads
    it: units, sample period, command matching, then one line per run."""
    loops = read_runs(bag, namespace=namespace, **reading)
    first = loops[0]
    scale = first.scale
    period = ('unknown (no simulator RunInfo, no --sample-period, and the stamps give none)'
              if first.h is None else f'h = {first.h:g} tau = '
              f'{scale.tau_to_seconds(first.h):.6g} s (from {H_SOURCES[first.h_source]})')
    lines = [f'bag:        {bag}',
             f'loop:       {first.namespace}',
             f'units:      orbit rate {scale.orbit_rate:g} rad/s, tether {scale.tether_length:g} '
             f'm, mass {scale.mass:g} kg ({UNITS_SOURCES[first.units]})',
             f'sample:     {period}',
             f'commands:   matched by {first.match}',
             f'runs:       {len(loops)}']
    for loop in loops:
        samples = max(loop.step.size - 1, 0)
        applied = int(np.isfinite(loop.u[:-1]).sum()) if samples else 0
        line = (f'  {loop.describe()}: {loop.counts["commands"]} commands, {applied} of '
                f'{samples} samples with a tension')
        held = int(loop.held[:-1].sum()) if samples else 0
        extra = [f'{held} held' if held else '',
                 f'{loop.counts["conflicting_states"]} conflicting states'
                 if loop.counts['conflicting_states'] else '',
                 f'{loop.halt_reason} at tau {loop.halt_tau:.2f}' if loop.halt_tau is not None
                 else (loop.halt_reason or '')]
        lines.append(line + ''.join(f', {e}' for e in extra if e))
    return lines


def info(bag):
    """Lines describing `bag` as read (files, topics, counts, time) and its metadata.yaml."""
    reader = BagReader(bag)
    counts, first, last = {}, None, None
    for msg in reader.messages():
        counts[msg.topic] = counts.get(msg.topic, 0) + 1
        first = msg.log_time_ns if first is None else min(first, msg.log_time_ns)
        last = msg.log_time_ns if last is None else max(last, msg.log_time_ns)
    report = reader.report
    start = datetime.datetime.fromtimestamp(first / 1e9, datetime.timezone.utc)
    lines = [f'bag:        {bag}',
             f'messages:   {report.messages}',
             f'start:      {start.isoformat()} ({first} ns)',
             f'duration:   {(last - first) / 1e9:.3f} s',
             'topics:']
    # Every topic with a channel, in the bag's order: one without messages is part of the bag.
    width = max(len(name) for name in reader.topics)
    lines += [f'  {name:<{width}}  {type_name}  {counts.get(name, 0)}'
              for name, type_name in reader.topics.items()]
    lines += ['files:'] + [f'  {f.line()}' for f in report.files]
    lines.append(f'{METADATA_FILE}: {_metadata_line(bag, report)}')
    return lines


def _metadata_line(bag, report):
    path = os.path.join(bag, METADATA_FILE)
    if not os.path.isdir(bag) or not os.path.exists(path):
        return 'none'
    try:
        meta = _bag_information(bag)
        listed, count = meta['relative_file_paths'], meta['message_count']
    except METADATA_ERRORS as err:
        return f'unreadable ({type(err).__name__}: {err})'.replace('\n', ' ')
    line = f'{len(listed)} files, {count} messages'
    if count != report.messages or sorted(listed) != sorted(f.path for f in report.files):
        line += ' (differs from the files: `bag recover` writes a complete bag)'
    return line
