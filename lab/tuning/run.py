"""tune(): a law's study opened (or refused), worker processes on it until it holds the trials
asked for, and its report; the Python function beneath `python -m lab.tune`."""

import dataclasses
import os

from lab.tuning.report import quiet, report
from lab.tuning.space import from_json
from lab.tuning.spec import fixed_settings, StudySpec
from lab.tuning.study import open_study
from lab.tuning.workers import run_workers

OUT = os.path.join('out', 'tune')


@dataclasses.dataclass(frozen=True)
class TuneResult:
    """A tuned study: its name and storage, its finished trials, the best trial's score and
    settings (as `make_controller(law, **settings)` takes them), the report's summary (the
    <study>.json) and text, and the files written."""
    study: str
    storage: str
    trials: int
    best_value: float
    settings: dict
    summary: dict
    text: str
    files: list


class Interrupted(KeyboardInterrupt):
    """Ctrl-C while the workers ran: they stored the trials in progress in `storage`."""

    def __init__(self, storage):
        super().__init__(storage)
        self.storage = storage


def default_storage(spec, out=OUT):
    """The journal file a study lives in when no --storage is given."""
    return os.path.join(out, spec.study_name + '.journal')


def tune(law, trials=60, jobs=1, storage=None, study=None, objective='settle', penalty='flat',
         starts='comparison', swing_max=0.8, steps=2000, seed=0, out=OUT, fix=(), also=(),
         progress=True):
    """Tune `law` until its study holds `trials` finished trials (resuming one that holds
    fewer), in `jobs` worker processes, and report: -> TuneResult.

    `storage`: a journal file (default <out>/<study>.journal) or an Optuna RDB URL
    (`postgresql://user:password@host:port/db`, `sqlite:///file.db`); `study`: its name
    (default: from the law and the options); `fix`: 'SETTING=VALUE' texts held out of the
    search; `also`: settings searched only when asked; `progress`: a progress bar and a line
    per scoring on stdout. ValueError (nothing run, the storage as it was): a bad option, a
    storage that is no journal or cannot be opened, a study tuned on another objective,
    penalty or set of starts. RuntimeError: a worker failed. Interrupted: Ctrl-C, once the
    workers stored the trials in progress (the same call resumes)."""
    spec = StudySpec(law, tuple(fix), tuple(also), objective, penalty, starts, swing_max,
                     steps, study)
    spec.check()
    storage = storage or default_storage(spec, out)
    fixed = fixed_settings(spec)
    opened = open_study(spec, storage, seed)
    try:
        run_workers(opened, spec, fixed, storage, trials, jobs, seed, progress)
    except KeyboardInterrupt:
        raise Interrupted(storage) from None
    summary, text, files = report(opened, spec, fixed, out, jobs,
                                  print if progress else quiet)
    return TuneResult(spec.study_name, storage, summary['trials'], summary['best_value'],
                      from_json(summary['best_settings']), summary, text, files)
