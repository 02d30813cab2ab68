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
