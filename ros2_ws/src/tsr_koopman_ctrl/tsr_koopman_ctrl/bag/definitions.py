"""What a rosbag2 bag stores about a topic: its type's full definition, type hash and QoS.

Definitions and hashes come from an installed ROS prefix (share/<pkg>/msg/<Type>.msg and .json),
found through the ament index.
"""

from dataclasses import dataclass, field
import json
import os
import re

import yaml

DEFINITION_SEPARATOR = '=' * 80
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
               'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'}
# An infinite QoS duration as Jazzy's rmw reports it (RMW_DURATION_INFINITE), and so rosbag2
# writes it.
_INFINITE_DURATION = {'sec': 9223372036, 'nsec': 854775807}
# The rmw QoS enums by value, named as metadata version 9 writes them (rmw's
# qos_string_conversions; rosbag2 PR #1476); a value past the end is 'unknown'.
_HISTORY = ('system_default', 'keep_last', 'keep_all')
_RELIABILITY = ('system_default', 'reliable', 'best_effort', 'unknown', 'best_available')
_DURABILITY = ('system_default', 'transient_local', 'volatile', 'unknown', 'best_available')
_LIVELINESS = ('system_default', 'automatic', 'manual_by_node', 'manual_by_topic', 'unknown',
               'best_available')


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
        """The profiles as the MCAP channel's `offered_qos_profiles` string holds them."""
        return (yaml.safe_dump(self.offered_qos, sort_keys=False, default_flow_style=False)
                if self.offered_qos else '')


def qos_dict(history, depth, reliability, durability, liveliness, deadline_ns, lifespan_ns,
             lease_ns, avoid_ros_namespace_conventions=False):
    """One offered QoS profile in rosbag2's YAML form of metadata version 9, from rmw's enum
    values (what rclpy reports): policies by name, durations as sec / nsec."""
    def duration(ns):
        if ns is None or ns <= 0 or ns >= 2 ** 63 - 1:
            return dict(_INFINITE_DURATION) if ns else {'sec': 0, 'nsec': 0}
        return {'sec': int(ns // 10 ** 9), 'nsec': int(ns % 10 ** 9)}

    def name(names, value):
        return names[int(value)] if 0 <= int(value) < len(names) else 'unknown'
    return {'history': name(_HISTORY, history), 'depth': int(depth),
            'reliability': name(_RELIABILITY, reliability),
            'durability': name(_DURABILITY, durability), 'deadline': duration(deadline_ns),
            'lifespan': duration(lifespan_ns), 'liveliness': name(_LIVELINESS, liveliness),
            'liveliness_lease_duration': duration(lease_ns),
            'avoid_ros_namespace_conventions': bool(avoid_ros_namespace_conventions)}


def _interface_file(type_name, suffix):
    from ament_index_python.packages import get_package_share_directory
    package, kind, name = type_name.split('/')
    return os.path.join(get_package_share_directory(package), kind, name + suffix)


# rosbag2_cpp/src/rosbag2_cpp/message_definitions/local_message_definition_source.cpp
# (ros2/rosbag2 tag 0.26.5, 6927adf5): the field types of a .msg text (MSG_FIELD_TYPE_REGEX) and
# the primitives that are not dependencies (PRIMITIVE_TYPES, where wstring is missing: rosbag2
# would look for a message 'pkg/wstring', find none and store no definition at all).
_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')


def message_definition(type_name, read_msg=None):
    """Full ros2msg definition of `pkg/msg/Type` exactly as rosbag2 (Jazzy) stores it: its .msg
    text, then each dependency once, depth first, as a newline, a separator line, 'MSG: ' and
    the dependency named as its field spells it ('std_msgs/Header'), and its .msg text.

    `LocalMessageDefinitionSource::get_full_text` in rosbag2_cpp (tag 0.26.5, file
    rosbag2_cpp/src/rosbag2_cpp/message_definitions/local_message_definition_source.cpp): a
    text's dependencies are a std::set, so they follow in name order, not field order; the texts
    are the files' own, unchanged. `read_msg(pkg/msg/Type)` returns a .msg text (default: the
    installed one)."""
    read_msg = read_msg or (lambda t: open(_interface_file(t, '.msg')).read())
    seen = set()

    def full_text(name, text):
        package = name.split('/')[0]
        result = text
        for dep in sorted(_dependencies(text, package)):
            if dep in seen:
                continue
            seen.add(dep)
            dep_package, dep_name = dep.split('/')[0], dep.split('/')[-1]
            result += f'\n{DEFINITION_SEPARATOR}\nMSG: {dep}\n'
            result += full_text(dep, read_msg(f'{dep_package}/msg/{dep_name}'))
        return result

    return full_text(type_name, read_msg(type_name))


def _dependencies(text, package):
    """The non-primitive field types of a .msg text as its fields spell them ('pkg/Type'; a
    bare 'Type' is in `package`), as rosbag2 finds them."""
    found = set()
    for match in _FIELD_TYPE.finditer(text):
        name = match.group(1)
        if name in _PRIMITIVES:
            continue
        found.add(name if '/' in name else f'{package}/{name}')
    return found


def type_hash(type_name):
    """The RIHS01 type description hash from the installed <Type>.json ('' if not found)."""
    try:
        with open(_interface_file(type_name, '.json')) as f:
            hashes = json.load(f)['type_hashes']
    except (OSError, KeyError, ValueError):
        return ''
    return next((h['hash_string'] for h in hashes if h['type_name'] == type_name), '')


def normalized_definition(text, type_name):
    """A full ros2msg definition reduced to what makes the type: {'pkg/Type': (declaration,
    ...)} for the type and every dependency, each declaration 'TYPE NAME', 'TYPE NAME DEFAULT'
    or 'TYPE NAME=VALUE' in the order written, types spelled 'pkg/Type'.

    Gone: comments, blank lines, whitespace, the separator and 'MSG:' spelling, 'pkg/msg/Type'
    against 'pkg/Type' (a bare 'Type' is in the section's package; 'Header' is
    std_msgs/Header) and the order of the dependencies, which differ between writers
    (rosbag2 sorts them by name). Kept: every field's type (arrays and bounds included), name
    and default, every constant's value, and their order."""
    sections, name, lines = {}, _short(type_name), []
    for line in text.replace('\r\n', '\n').split('\n'):
        stripped = line.strip()
        if len(stripped) >= 3 and set(stripped) == {'='}:
            sections[name] = lines
            name, lines = None, []
        elif name is None and stripped:
            kind, _, dep = stripped.partition(':')
            name = _short(dep.strip()) if kind.strip() == 'MSG' else stripped
        else:
            lines.append(line)
    sections[name] = lines
    return {section: tuple(filter(None, (_declaration(line, section.split('/')[0])
                                         for line in body)))
            for section, body in sections.items()}


def definition_difference(recorded, installed, type_name):
    """'' if two full definitions of `type_name` declare the same type (`normalized_definition`),
    else where they first differ, in a few words."""
    ours, theirs = (normalized_definition(t, type_name) for t in (recorded, installed))
    for section in [_short(type_name)] + sorted(set(ours) | set(theirs)):
        if section not in ours or section not in theirs:
            where = 'the bag' if section in ours else 'the installed one'
            return f'{section} is a dependency only in {where}'
        a, b = ours[section], theirs[section]
        if a != b:
            i = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
            here = repr(a[i]) if i < len(a) else 'nothing'
            there = repr(b[i]) if i < len(b) else 'nothing'
            return f'{section} declaration {i + 1}: {here} in the bag, {there} installed'
    return ''


def _short(type_name):
    """'pkg/msg/Type' or 'pkg/Type' -> 'pkg/Type'."""
    parts = type_name.split('/')
    return f'{parts[0]}/{parts[-1]}' if len(parts) > 1 else type_name


def _declaration(line, package):
    """One .msg line as 'TYPE NAME[ DEFAULT]' or 'TYPE NAME=VALUE', comments and whitespace
    gone ('' for a blank or comment line)."""
    line = _uncommented(line).strip()
    if not line:
        return ''
    type_token, _, rest = line.partition(' ') if ' ' in line else line.partition('\t')
    rest = rest.strip()
    name, equals, value = rest.partition('=')
    if equals and ' ' not in name.strip():           # a constant: NAME=VALUE, NAME = VALUE
        return f'{_field_type(type_token, package)} {name.strip()}={value.strip()}'
    return ' '.join([_field_type(type_token, package)] + rest.split())


def _uncommented(line):
    """The line up to its comment: a '#' outside quotes (a string constant may hold one)."""
    quote = None
    for i, char in enumerate(line):
        if quote:
            quote = None if char == quote else quote
        elif char in '"\'':
            quote = char
        elif char == '#':
            return line[:i]
    return line


def _field_type(token, package):
    base, bracket, array = token.partition('[')
    bound = ''
    if '<=' in base:                                  # string<=10
        base, bound = base.split('<=', 1)
        bound = '<=' + bound
    if base in _PRIMITIVES:
        pass
    elif '/' in base:
        base = _short(base)
    elif base == 'Header':
        base = 'std_msgs/Header'
    else:
        base = f'{package}/{base}'
    return base + bound + bracket + array
