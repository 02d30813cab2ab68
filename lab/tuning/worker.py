"""One worker process on a study (started by `workers.start`, multiprocessing spawn): trials
until its share is run, the study holds its target of finished trials, a stop is asked (Ctrl-C)
or the tune process that started it is gone."""

import dataclasses
import os
import signal
import socket

from lab.tuning.scoring import score
from lab.tuning.space import as_json, suggest
from lab.tuning.spec import StudySpec
from lab.tuning.study import DONE, finished, open_study


@dataclasses.dataclass(frozen=True)
class Job:
    """A worker's orders: the study (`spec`, its parsed `fixed` settings, `storage`), the
    finished trials the study is to hold (`target`), the most trials this worker runs
    (`share`), its sampler's seed and the pid of the tune process that started it."""
    spec: StudySpec
    fixed: dict
    storage: str
    target: int
    share: int
    seed: int
    parent: int


def work(job):
    """The worker process's entry. Ctrl-C reaches the workers too (one process group): the
    first lets the trial in progress finish and be stored, a second abandons it (the tune
    process says which)."""
    requested = []

    def on_interrupt(signum, frame):
        if requested:
            raise KeyboardInterrupt
        requested.append(signum)
    signal.signal(signal.SIGINT, on_interrupt)
    try:
        run(job, requested)
    except KeyboardInterrupt:
        pass


def run(job, requested=()):
    """Trials of `job` until one of its ends; `requested`: a list that is not empty once a stop
    was asked."""
    from optuna.study import MaxTrialsCallback
    from optuna.trial import TrialState
    study = open_study(job.spec, job.storage, job.seed)
    spec = job.spec
    # host:pid names the process a trial ran in (a RUNNING trial whose worker is gone is one
    # that was killed).
    name = f'{socket.gethostname()}:{os.getpid()}'

    def objective(trial):
        trial.set_user_attr('worker', name)
        settings = suggest(trial, spec.law, job.fixed, spec.also)
        value, runs = score(spec.law, settings, spec.tuning_starts, spec.swing_max, spec.steps,
                            spec.objective, spec.graded)
        trial.set_user_attr('settings', as_json(settings))
        trial.set_user_attr('settle', [r.get('settle_tau') for r in runs])
        trial.set_user_attr('swing', [r.get('swing') for r in runs])
        return value

    if requested or finished(study) >= job.target:
        return
    # The cap stops this worker once other commands on the study (another machine's) have
    # filled it; its share keeps the workers of one command from running more than asked.
    states = tuple(getattr(TrialState, state) for state in DONE)
    study.optimize(objective, n_trials=job.share,
                   callbacks=[MaxTrialsCallback(job.target, states=states),
                              stop_when(requested, job.parent)])


def stop_when(requested, parent):
    """An Optuna callback that stops the worker after its current trial when a stop was
    `requested` (a list that is not empty) or `parent`, the tune process that started it, is
    gone: a killed command must not leave its workers running unseen."""
    def check(study, trial):
        if requested or os.getppid() != parent:
            study.stop()
    return check
