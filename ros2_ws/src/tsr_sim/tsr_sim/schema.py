"""Parameter schemas, declared once: a frozen dataclass per group of parameters (a law's
settings, the plant's, a node's own) whose fields carry their default, a one-line description
and a range or choices (`setting`). A node's ROS parameters (`ros_io.declare_schema`), the
tools' command-line values (`parse_value`), the example parameter files (`parameter_lines`)
and the checks of a plant file are derived from these classes; a name none of them has is
refused with one hint (`did_you_mean`). ROS-free.
"""

import dataclasses
import difflib
import math
import numbers
import types
from typing import ClassVar

#: When a node applies a new value of a parameter: at start only (read-only on a running
#: node), at configure (a lifecycle node: settable while unconfigured, refused otherwise) or
#: live (applied when set).
AT_START, AT_CONFIGURE, LIVE = 'start', 'configure', 'live'


def setting(default, description, low=None, high=None, choices=None, tune=None,
            searched=True, fixed_length=True, applied=AT_START):
    """A schema field: its default, a one-line description with units, a range or choices.
    A sequence default (a tuple or a list) takes that many values (`fixed_length` False: any
    number of them). `tune`: the search space of lab/tune.py, (low, high, 'log' or 'linear')
    for a number or for every component of a sequence, a list of such triples (one per
    component), or a list of choices for a string; None: not tuned. `searched` False:
    lab/tune.py searches it only when asked (`--also NAME`), so the studies recorded without
    it stay reproducible. `applied`: AT_START, AT_CONFIGURE or LIVE (a node may declare a whole
    class otherwise: the controller reads every law's settings at configure)."""
    if isinstance(default, list):
        default = tuple(default)
    sized = isinstance(default, tuple) and fixed_length
    return dataclasses.field(default=default, metadata={
        'description': description, 'low': low, 'high': high, 'choices': choices,
        'size': len(default) if sized else None, 'tune': tune, 'searched': searched,
        'applied': applied})


@dataclasses.dataclass(frozen=True)
class Settings:
    """Base of every schema class: checks types, ranges and choices when built (one line
    naming the parameter)."""

    #: The section its names are under (`koopman_mpc` of `koopman_mpc.horizon`); '': none.
    section: ClassVar[str] = ''

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, list):
                value = tuple(value)
                object.__setattr__(self, field.name, value)
            check_value(type(self), field, value)


def section_name(schema):
    """The section a schema class's names are under ('' for none); a plain dataclass's name."""
    return getattr(schema, 'section', schema.__name__)


def parameter_name(schema, name):
    """`<section>.<name>`, or `name` for a schema without a section."""
    section = section_name(schema)
    return f'{section}.{name}' if section else name


def _owner(schema):
    return section_name(schema) or schema.__name__


def did_you_mean(name, candidates, cutoff=0.6, prefix=''):
    """" (did you mean '<prefix><closest>'?)" naming the candidate closest to `name`, or ''
    when none is close enough: the one hint every refusal of an unknown name gives."""
    close = difflib.get_close_matches(str(name), [str(c) for c in candidates], n=1,
                                      cutoff=cutoff)
    return f" (did you mean '{prefix}{close[0]}'?)" if close else ''


def _is_number(value):
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_strings(default):
    return isinstance(default, tuple) and bool(default) and all(
        isinstance(v, str) for v in default)


def _type_fits(default, value):
    """True if `value` has the type of the setting whose default is `default` (an int where a
    float is wanted is fine; a string or bool where a number is wanted is not). Strings are not
    checked: a law's `model` also takes a loaded LiftedModel, and choices are checked apart."""
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, int):
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if isinstance(default, float):
        return _is_number(value)
    if _is_strings(default):
        return isinstance(value, tuple) and all(isinstance(v, str) for v in value)
    if isinstance(default, tuple):
        return isinstance(value, tuple) and all(_is_number(v) for v in value)
    return True


def _kind(field):
    default, size = field.default, field.metadata.get('size')
    if isinstance(default, bool):
        return 'true or false'
    if isinstance(default, int):
        return 'an integer'
    if isinstance(default, float):
        return 'a number'
    if _is_strings(default):
        return 'a list of strings'
    return f'{size} numbers' if size is not None else 'a list of numbers'


def check_value(schema, field, value):
    """Raise ValueError (one line naming the parameter) if `value` is of another type than the
    field's default, out of range or not one of the choices."""
    meta = field.metadata
    where = parameter_name(schema, field.name)
    if not _type_fits(field.default, value):
        raise ValueError(f'{where} must be {_kind(field)}, got {value!r}')
    if meta.get('choices') and value not in meta['choices']:
        raise ValueError(f'{where} must be one of {list(meta["choices"])}, got {value!r}')
    if meta.get('size') is not None and (not isinstance(value, tuple)
                                         or len(value) != meta['size']):
        raise ValueError(f'{where} needs {meta["size"]} numbers, got {value!r}')
    for number in value if isinstance(value, tuple) else (value,):
        if isinstance(number, (int, float)) and not isinstance(number, bool):
            if not math.isfinite(number):
                raise ValueError(f'{where} must be finite, got {value!r}')
            if meta.get('low') is not None and number < meta['low']:
                raise ValueError(f'{where} must be >= {meta["low"]}, got {value!r}')
            if meta.get('high') is not None and number > meta['high']:
                raise ValueError(f'{where} must be <= {meta["high"]}, got {value!r}')


def fields(schema):
    """[(name, default, metadata)] of a schema class, in declaration order."""
    return [(f.name, f.default, f.metadata) for f in dataclasses.fields(schema)]


def _refuse_unknown(schema, name, known):
    raise ValueError(f'{_owner(schema)} has no setting {name!r}{did_you_mean(name, known)}; '
                     f'settings: {sorted(known)}')


def build(schema, settings=None, overrides=None):
    """Settings from an instance (or None: the defaults) with `overrides` applied and checked."""
    base = settings if settings is not None else schema()
    if not isinstance(base, schema):
        raise TypeError(f'expected {schema.__name__}, got {type(base).__name__}')
    overrides = dict(overrides or {})
    known = [f.name for f in dataclasses.fields(schema)]
    unknown = sorted(set(overrides) - set(known))
    if unknown:
        _refuse_unknown(schema, unknown[0], known)
    return dataclasses.replace(base, **overrides)


def unknown_setting_names(names, sections):
    """Lines naming each of `names` (parameter names given to a node) that starts with one of
    `sections` ({section: schema class}, e.g. the laws, 'observer') but names none of that
    section's settings. ROS drops a parameter no node declares without a word, so a misspelt
    `koopman_mpc.horizn` would deploy the default horizon. Names of other sections, or of none,
    are left alone: a shared `/**` file holds other nodes' parameters too."""
    problems = []
    for name in sorted(names):
        section, dot, setting_name = name.partition('.')
        if not dot or section not in sections:
            continue
        known = [field.name for field in dataclasses.fields(sections[section])]
        if setting_name not in known:
            hint = did_you_mean(setting_name, known, prefix=f'{section}.')
            problems.append(f"parameter '{name}': {section} has no setting "
                            f"'{setting_name}'{hint}")
    return problems


def parse_value(schema, name, text):
    """A CLI string -> the setting's type (numbers, 'a,b,c' for sequences, strings), checked
    against nothing else (building the settings checks ranges and choices)."""
    defaults = {n: d for n, d, _ in fields(schema)}
    if name not in defaults:
        _refuse_unknown(schema, name, list(defaults))
    default = defaults[name]
    try:
        if isinstance(default, bool):
            if text.lower() not in ('true', 'false'):
                raise ValueError(text)
            return text.lower() == 'true'
        if _is_strings(default):
            return tuple(text.split(','))
        if isinstance(default, tuple):
            return tuple(float(v) for v in text.split(','))
        if isinstance(default, int):
            return int(text)
        if isinstance(default, float):
            return float(text)
    except ValueError:
        raise ValueError(f'{parameter_name(schema, name)}: cannot read {text!r} as '
                         f'{type(default).__name__}')
    return text


def parse_assignments(assignments, section_class):
    """{section: {setting: value}} from 'SECTION.SETTING=VALUE' strings (deploy's --set, the
    lab's), each value read as its setting's type (`parse_value`) and checked; ValueError, one
    line, for a malformed assignment, an unknown section or setting, or a bad value.
    `section_class(section)`: the schema class of a section (ValueError for an unknown one)."""
    settings = {}
    for assignment in assignments:
        key, sep, text = assignment.partition('=')
        section, dot, name = key.partition('.')
        if not (sep and dot):
            raise ValueError(f'--set takes SECTION.SETTING=VALUE, got {assignment!r}')
        settings.setdefault(section, {})[name] = parse_value(section_class(section), name,
                                                             text)
    return settings


def parameter_table(schema):
    """A read-only {name: (default, description, low, high)} view of a schema class (a
    sequence default as a list, as a parameter file writes it)."""
    return types.MappingProxyType({
        name: (list(default) if isinstance(default, tuple) else default,
               meta['description'], meta['low'], meta['high'])
        for name, default, meta in fields(schema)})


def names_applied(applied, *schemas):
    """The names of the fields of `schemas` a node applies `applied` (e.g. LIVE)."""
    return tuple(name for schema in schemas for name, _, meta in fields(schema)
                 if meta.get('applied', AT_START) == applied)


def yaml_value(value):
    """A default as a parameter file writes it (a string in a list quoted, as rcl reads a list
    of one type only)."""
    if isinstance(value, (tuple, list)):
        return f'[{", ".join(repr(v) if isinstance(v, str) else yaml_value(v) for v in value)}]'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value or "''"
    return repr(float(value)) if isinstance(value, float) else str(value)


def parameter_lines(schema, indent, defaults=None):
    """Lines of a parameter file for a schema class at `indent`: each field's description as
    a comment above its default. `defaults`: {name: text} for a default a node computes, as a
    commented-out line (a value written there would no longer follow the units)."""
    lines = []
    for name, default, meta in fields(schema):
        lines.append(f'{indent}# {meta["description"]}')
        if defaults and name in defaults:
            lines.append(f'{indent}# {name}: {defaults[name]}')
        else:
            lines.append(f'{indent}{name}: {yaml_value(default)}')
    return lines
