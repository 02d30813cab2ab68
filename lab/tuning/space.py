"""The search space: each setting's `tune` entry in its law's Settings class (the one
declaration), sampled per trial and written back as Optuna parameters."""

from tsr_koopman_ctrl.control.registry import law_class
from tsr_koopman_ctrl.control.settings import fields


def tunable(law, also=()):
    """[(setting, default, tune spec)] of a law: the settings searched by default and those
    named in `also` (searched only when asked, e.g. q_cross)."""
    return [(name, default, meta['tune']) for name, default, meta in
            fields(law_class(law).Settings) if meta.get('tune') is not None
            and (meta.get('searched', True) or name in also)]


def searchable(law):
    """The settings of a law that have a `tune` entry, searched by default or not."""
    return {name for name, _, meta in fields(law_class(law).Settings)
            if meta.get('tune') is not None}


def suggest(trial, law, fixed=None, also=()):
    """Settings of a trial, sampled from each setting's `tune` entry; `fixed`: {setting: value}
    held out of the search; `also`: settings searched only when asked."""
    settings = dict(fixed or {})
    for name, default, spec in tunable(law, also):
        if name in settings:
            continue
        if isinstance(spec, list) and spec and isinstance(spec[0], str):
            settings[name] = trial.suggest_categorical(name, spec)
        elif isinstance(default, tuple):
            specs = spec if isinstance(spec, list) else [spec] * len(default)
            settings[name] = tuple(number(trial, f'{name}_{i}', s) for i, s in enumerate(specs))
        else:
            settings[name] = number(trial, name, spec, integer=isinstance(default, int))
    return settings


def number(trial, name, spec, integer=False):
    low, high, scale = spec
    if integer:
        return trial.suggest_int(name, int(low), int(high), log=scale == 'log')
    return trial.suggest_float(name, low, high, log=scale == 'log')


def as_params(law, settings, fixed=None, also=()):
    """The inverse of `suggest`: Optuna parameters of given settings (to enqueue a trial)."""
    params = {}
    for name, default, spec in tunable(law, also):
        if name in (fixed or {}):
            continue
        value = settings.get(name, default)
        if isinstance(value, tuple):
            params.update({f'{name}_{i}': v for i, v in enumerate(value)})
        else:
            params[name] = value
    return params


def as_json(settings):
    """Settings as JSON stores them (tuples as lists)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()}


def from_json(settings):
    """The inverse of `as_json`: the lists back to tuples, as the laws take them."""
    return {k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()}
