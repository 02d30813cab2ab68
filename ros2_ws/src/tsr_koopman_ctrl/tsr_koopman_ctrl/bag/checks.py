"""What a bag can be trusted with, checked before any of its data is used: its files found,
its content hashed (files and messages), its loop's types against the installed definitions.

    from tsr_koopman_ctrl.bag import checks
    paths = checks.find_bags(['bags/'])       # a bag, one .mcap file, or every bag below
                                              # (but those of failed deployments)
    counts, types, digest = checks.scan(path, BagReader(path))

A type recorded with another definition than the installed one, a state or command that does
not decode, a bag without the loop's types: `BagDataError`, one line naming the bag.
"""

import collections
import functools
import hashlib
import os
import warnings

from tsr_sim import wire

from tsr_koopman_ctrl.bag import definitions
from tsr_koopman_ctrl.bag.reader import bag_files
from tsr_koopman_ctrl.bag.tsr_loop import BagWarning, loop_namespace, STATE_TYPE, TENSION_TYPE

#: Types whose definition must match the installed one: a loop is read from them.
CHECKED_TYPES = (STATE_TYPE, TENSION_TYPE)


class BagDataError(ValueError):
    """A bag that cannot give training data; str() is one line naming the bag."""

    def __init__(self, bag, what):
        super().__init__(f'{bag}: {what}')
        self.bag, self.what = str(bag), what


#: The file a failed deployment leaves in its bag, saying why it failed: the bag is kept as
#: recorded, for a look at what went wrong, but it is no training data.
FAILED_MARK = 'failed_deployment.txt'


def mark_failed(bag, reason):
    """Mark `bag` as the record of a failed deployment (`FAILED_MARK`, holding `reason`)."""
    with open(os.path.join(bag, FAILED_MARK), 'w') as mark:
        mark.write(reason.rstrip('\n') + '\n')


def is_failed(bag):
    return os.path.isfile(os.path.join(bag, FAILED_MARK))


def find_bags(paths, skipped=None):
    """The bags named by `paths`, each once, in order: a bag directory (its .mcap files), one
    .mcap file, or a directory holding bags anywhere below it (sorted). A directory counts as a
    bag if it holds .mcap files or a rosbag2 metadata.yaml (then an empty bag is reported as
    such). Below a directory, the bags of failed deployments (`mark_failed`) are skipped, each
    with one line appended to `skipped` (a list; None: a BagWarning); named themselves, they
    are read. Raises BagDataError for a path that names no bag."""
    found, seen = [], set()
    for path in paths:
        path = os.fspath(path)
        if not os.path.exists(path):
            raise BagDataError(path, 'no such file or directory')
        if os.path.isfile(path):
            if not path.endswith('.mcap'):
                raise BagDataError(path, 'not a bag (a bag is a directory of .mcap files or '
                                   'one .mcap file)')
            bags = [path]
        else:
            bags = sorted(directory for directory, _, names in os.walk(path, followlinks=True)
                          if 'metadata.yaml' in names or any(n.endswith('.mcap') for n in names))
            failed = [bag for bag in bags if bag != path and is_failed(bag)]
            for bag in failed:
                line = (f'skipped {bag}: the bag of a failed deployment ({FAILED_MARK} says '
                        'why; name the bag itself to read it)')
                if skipped is None:
                    warnings.warn(line, BagWarning, stacklevel=2)
                else:
                    skipped.append(line)
            bags = [bag for bag in bags if bag not in failed]
            if not bags:
                raise BagDataError(path, 'no bag below it (no .mcap files)' if not failed else
                                   'no bag below it but those of failed deployments '
                                   f'({len(failed)} skipped)')
        for bag in bags:
            key = os.path.realpath(bag)
            if key not in seen:
                seen.add(key)
                found.append(bag)
    return found


def content_hash(path):
    """(sha256 of the bag's .mcap files' bytes concatenated in split order, one entry per file
    with its own sha256 and size): what identifies the data, whatever the bag is called."""
    total, files = hashlib.sha256(), []
    for name in bag_files(path) if os.path.exists(path) else []:
        digest, size = hashlib.sha256(), 0
        with open(name, 'rb') as stream:
            for block in iter(lambda: stream.read(1 << 20), b''):
                digest.update(block)
                total.update(block)
                size += len(block)
        files.append({'file': os.path.basename(name), 'sha256': digest.hexdigest(),
                      'bytes': size})
    return total.hexdigest(), files


class MessagesHash:
    """sha256 of a bag's messages as recorded: per topic, its type and every payload in order;
    the topics in name order. What identifies the data when the files do not: `bag recover` or
    another chunking writes the same messages into other bytes (and may interleave the topics
    differently); log times and file layout are left out."""

    def __init__(self):
        self.topics = {}

    def add(self, topic, type_name, data):
        digest = self.topics.get(topic)
        if digest is None:
            digest = self.topics[topic] = hashlib.sha256()
        # Length-prefixed, so that no two message sequences hash the same bytes.
        digest.update(type_name.encode() + b'\0' + len(data).to_bytes(8, 'little'))
        digest.update(data)

    def hexdigest(self):
        total = hashlib.sha256()
        for topic in sorted(self.topics):
            total.update(f'{topic}\0{self.topics[topic].hexdigest()}\n'.encode())
        return total.hexdigest()


@functools.lru_cache(maxsize=None)
def installed_definition(type_name):
    """The definition this build would record for `type_name` (the ament index's .msg files)."""
    try:
        return definitions.message_definition(type_name)
    except Exception as error:         # package not found, file missing: not the bag's fault
        raise ValueError(f'cannot check bags: the installed definition of {type_name} is not '
                         f'found ({type(error).__name__}: {error}); is the workspace sourced?')


@functools.lru_cache(maxsize=None)
def installed_hash(type_name):
    """The installed RIHS01 type hash of `type_name` ('' if the build has none)."""
    return definitions.type_hash(type_name)


def check_definition(bag, type_name, text, recorded_hash=''):
    """Refuse a type recorded with another definition than the installed one.

    By the RIHS01 type hash when the bag (channel or metadata.yaml) and the installation both
    have one: it is what ROS itself compares. Else by the definitions normalised
    (`definitions.normalized_definition`): writers spell the same type differently (rosbag2:
    'MSG: std_msgs/Header', a blank line before each separator, dependencies sorted by name), so
    only field types, names, defaults, constants and their order are compared. Comments are
    left out although ours carry units: the type hash leaves them out too (a hash match says
    nothing about them), and units on the wire are REP 103 SI by convention, which no comment
    changes; a bag's own scale is its RunInfo, checked apart."""
    ours = installed_hash(type_name)
    if recorded_hash and ours:
        if recorded_hash == ours:
            return
        difference = f'type hash {recorded_hash} in the bag, {ours} installed'
    else:
        difference = definitions.definition_difference(
            text, installed_definition(type_name), type_name)
        if not difference:
            return
    raise BagDataError(bag, f'{type_name} was recorded with another message definition than '
                       f'the installed one ({difference})')


def scan(bag, reader):
    """One pass over the bag: message counts per topic, the topic types, the hash of the
    messages (`MessagesHash`), and every state and command checked (its definition against the
    installed one, then that it decodes)."""
    from mcap_ros2.decoder import DecoderFactory
    factory, decoders, checked = DecoderFactory(), {}, {}
    counts, types, digest = collections.Counter(), {}, MessagesHash()
    for msg in reader.messages():
        counts[msg.topic] += 1
        digest.add(msg.topic, msg.type, msg.data)
        types.setdefault(msg.topic, set()).add(msg.type)
        if msg.type not in CHECKED_TYPES:
            continue
        schema = reader.schemas[msg.type]
        type_hash = reader.type_hash(msg.topic)
        # Every file of a bag has its own schema, every topic its own hash.
        if checked.get((msg.type, type_hash)) is not schema:
            check_definition(bag, msg.type, schema.data.decode('utf-8', 'replace'), type_hash)
            checked[msg.type, type_hash] = schema
            decoders[msg.type] = factory.decoder_for('cdr', schema)
        try:
            decoders[msg.type](msg.data)
        except Exception as error:
            raise BagDataError(bag, f'message {counts[msg.topic]} on {msg.topic} does not '
                               f'decode as {msg.type} ({type(error).__name__})')
    return counts, types, digest.hexdigest()


def loop_topics(bag, types, namespace):
    """The loop's namespace in a bag whose topics have `types` ({topic: {type}}), checking that
    it has states and commands of the project's types there (BagDataError otherwise)."""
    by_type = collections.defaultdict(set)
    for topic, names in types.items():
        for name in names:
            by_type[name].add(topic)
    listed = ', '.join(f'{t} [{"/".join(sorted(n))}]' for t, n in sorted(types.items()))
    for wanted in CHECKED_TYPES:
        if wanted not in by_type:
            raise BagDataError(bag, f'wrong types: no {wanted} messages (topics: '
                               f'{listed or "none"})')
    try:
        namespace = loop_namespace(by_type[STATE_TYPE], namespace)
    except ValueError as error:
        raise BagDataError(bag, str(error).removeprefix('bag ')) from None
    for topic, wanted in ((wire.STATE_TOPIC, STATE_TYPE), (wire.TENSION_TOPIC, TENSION_TYPE)):
        name = wire.resolve(topic, namespace)
        if name not in by_type[wanted]:
            raise BagDataError(bag, f'wrong types: no {wanted} messages on {name} (topics: '
                               f'{listed})')
    return namespace
