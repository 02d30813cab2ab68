"""Opening a study: created with the options it is tuned on, or loaded and refused where it was
tuned on others, the storage left as it was then."""

from lab.tuning.spec import RECORDED
from lab.tuning.storage import open_storage

DONE = ('COMPLETE', 'FAIL')


def open_study(spec, storage, seed=0):
    """The Optuna study of `spec` in `storage` (a journal path or a database URL), sampled by
    TPE from `seed`; ValueError where the study was tuned on another objective, penalty or set
    of starts."""
    import optuna
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    backend = open_storage(storage)
    sampler = optuna.samplers.TPESampler(seed=seed)
    name = spec.study_name
    if name in optuna.study.get_all_study_names(backend):
        # Loaded, not created again: create_study(load_if_exists=True) appends a record to a
        # journal even when the study is there, so a refused resume changed the file.
        study = optuna.load_study(study_name=name, storage=backend, sampler=sampler)
    else:
        study = optuna.create_study(study_name=name, storage=backend, direction='minimize',
                                    load_if_exists=True, sampler=sampler)
    check_options(study, spec)
    return study


def check_options(study, spec):
    """Record the spec's options in a new study; ValueError where a study holds others (settle
    times and ratios in one study would be compared)."""
    recorded = {option: study.user_attrs.get(option, default if study.trials else None)
                for option, default in RECORDED.items()}
    for option, value in recorded.items():
        if value is not None and value != getattr(spec, option):
            raise ValueError(f'study {spec.study_name!r} was tuned on --{option} {value}, '
                             f'not {getattr(spec, option)}')
    for option, value in recorded.items():
        if value is None:
            study.set_user_attr(option, getattr(spec, option))


def finished(study):
    """The study's trials that count against --trials: complete, or failed (abandoned by a
    second Ctrl-C); a killed worker's trial stays RUNNING and does not count."""
    return sum(t.state.name in DONE for t in study.get_trials(deepcopy=False))
