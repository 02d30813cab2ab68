"""Each law's settings, declared once: a frozen dataclass per law whose fields carry their
description and range. The controller node's parameters (``<law>.<field>``), the tools' CLI flags
(``--set <law>.<field>=<value>``, read by `parse_assignments`) and the example config file are
all derived from these classes.
"""

import dataclasses
import difflib
import math
import numbers


def setting(default, description, low=None, high=None, choices=None, tune=None,
            searched=True):
    """A settings field: its default, a one-line description with units, a range or choices.
    A sequence default (a tuple) fixes the number of values the setting takes. `tune`: the
    search space of lab/tune.py, (low, high, 'log' or 'linear') for a number or for every
    component of a sequence, a list of such triples (one per component), or a list of choices
    for a string; None: not tuned. `searched` False: lab/tune.py searches it only when asked
    (`--also NAME`), so the studies recorded without it stay reproducible."""
    if isinstance(default, list):
        default = tuple(default)
    return dataclasses.field(default=default, metadata={
        'description': description, 'low': low, 'high': high, 'choices': choices,
        'size': len(default) if isinstance(default, tuple) else None, 'tune': tune,
        'searched': searched})


def cross_weight_setting(search_bound=10.0):
    """The state weight's cross terms, declared once for every law with a quadratic cost on
    the state (`control.lqr.state_cost_matrix`); lab/tune.py searches each in
    [-search_bound, search_bound] when asked (`--also q_cross`)."""
    return setting((0.0,) * 6, 'cross terms of the state weight Q = L L^T: the entries of L '
                   'below its diagonal sqrt(q), row by row (L10, L20, L21, L30, L31, L32); '
                   'zeros: Q = diag(q)', tune=(-search_bound, search_bound, 'linear'),
                   searched=False)


@dataclasses.dataclass(frozen=True)
class LawSettings:
    """Base of every law's settings: checks ranges and choices when built."""

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, list):
                value = tuple(value)
                object.__setattr__(self, field.name, value)
            check_value(type(self), field, value)


def _is_number(value):
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _type_fits(default, value):
    """True if `value` has the type of the setting whose default is `default` (an int where a
    float is wanted is fine; a string or bool where a number is wanted is not). Strings are not
    checked: `model` also takes a loaded LiftedModel, and choices are checked apart."""
    if isinstance(default, bool):
        return isinstance(value, bool)
    if isinstance(default, int):
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if isinstance(default, float):
        return _is_number(value)
    if isinstance(default, tuple):
        return isinstance(value, tuple) and all(_is_number(v) for v in value)
    return True


def check_value(settings_class, field, value):
    """Raise ValueError (one line naming the setting) if `value` is of another type than the
    setting's default, out of range or not one of the choices."""
    meta = field.metadata
    where = f'{law_name(settings_class)}.{field.name}'
    default = field.default
    if not _type_fits(default, value):
        kind = ('true or false' if isinstance(default, bool) else
                'an integer' if isinstance(default, int) else
                'a number' if isinstance(default, float) else
                f'{len(default)} numbers')
        raise ValueError(f'{where} must be {kind}, got {value!r}')
    if meta.get('choices') and value not in meta['choices']:
        raise ValueError(f'{where} must be one of {list(meta["choices"])}, got {value!r}')
    if meta.get('size') is not None and (not isinstance(value, tuple)
                                         or len(value) != meta['size']):
        raise ValueError(f'{where} needs {meta["size"]} numbers, got {value!r}')
    numbers = value if isinstance(value, tuple) else (value,)
    for number in numbers:
        if isinstance(number, (int, float)) and not isinstance(number, bool):
            if not math.isfinite(number):
                raise ValueError(f'{where} must be finite, got {value!r}')
            if meta.get('low') is not None and number < meta['low']:
                raise ValueError(f'{where} must be >= {meta["low"]}, got {value!r}')
            if meta.get('high') is not None and number > meta['high']:
                raise ValueError(f'{where} must be <= {meta["high"]}, got {value!r}')


def law_name(settings_class):
    """The registry name a settings class belongs to (its `law` class attribute)."""
    return getattr(settings_class, 'law', settings_class.__name__)


def fields(settings_class):
    """[(name, default, metadata)] of a law's settings, in declaration order."""
    return [(f.name, f.default, f.metadata) for f in dataclasses.fields(settings_class)]


def build(settings_class, settings=None, overrides=None):
    """Settings from an instance (or None: the defaults) with `overrides` applied and checked."""
    base = settings if settings is not None else settings_class()
    if not isinstance(base, settings_class):
        raise TypeError(f'expected {settings_class.__name__}, got {type(base).__name__}')
    overrides = dict(overrides or {})
    known = {f.name for f in dataclasses.fields(settings_class)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f'{law_name(settings_class)} has no setting {unknown[0]!r}; '
                         f'settings: {sorted(known)}')
    return dataclasses.replace(base, **overrides)


def unknown_setting_names(names, sections):
    """Lines naming each of `names` (parameter names given to a node) that starts with one of
    `sections` ({section: settings class}, e.g. the laws, 'observer') but names none of that
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
            close = difflib.get_close_matches(setting_name, known, n=1)
            hint = f" (did you mean '{section}.{close[0]}'?)" if close else ''
            problems.append(f"parameter '{name}': {section} has no setting "
                            f"'{setting_name}'{hint}")
    return problems


def parse_value(settings_class, name, text):
    """A CLI string -> the setting's type (numbers, 'a,b,c' for sequences, strings), checked."""
    defaults = {n: d for n, d, _ in fields(settings_class)}
    if name not in defaults:
        raise ValueError(f'{law_name(settings_class)} has no setting {name!r}; settings: '
                         f'{sorted(defaults)}')
    default = defaults[name]
    try:
        if isinstance(default, bool):
            if text.lower() not in ('true', 'false'):
                raise ValueError(text)
            return text.lower() == 'true'
        if isinstance(default, tuple):
            return tuple(float(v) for v in text.split(','))
        if isinstance(default, int):
            return int(text)
        if isinstance(default, float):
            return float(text)
    except ValueError:
        raise ValueError(f'{law_name(settings_class)}.{name}: cannot read {text!r} as '
                         f'{type(default).__name__}')
    return text


def parse_assignments(assignments, section_class=None):
    """{section: {setting: value}} from 'SECTION.SETTING=VALUE' strings (deploy's --set, the
    lab's), each value read as its setting's type (`parse_value`) and checked; ValueError, one
    line, for a malformed assignment, an unknown section or setting, or a bad value.
    `section_class(section)`: the settings class of a section (default: the registry's
    `settings_class`: a law's, the observer's, the excitation's or the supervisor's)."""
    if section_class is None:
        from tsr_koopman_ctrl.control.registry import settings_class as section_class
    settings = {}
    for assignment in assignments:
        key, sep, text = assignment.partition('=')
        section, dot, name = key.partition('.')
        if not (sep and dot):
            raise ValueError(f'--set takes SECTION.SETTING=VALUE, got {assignment!r}')
        settings.setdefault(section, {})[name] = parse_value(section_class(section), name,
                                                             text)
    return settings
