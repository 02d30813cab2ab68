"""Tuning a law's settings with Optuna, the same way for every law (`python -m lab.tune` is the
command, `tune()` the function beneath it), one job a module:

- space: the search space, each setting's `tune` entry in its law's Settings class;
- scoring: a trial's score on the tuning starts, per objective and penalty;
- spec: what defines a study (law, fixed settings, objective, penalty, starts) and its name;
- storage: where a study lives, a journal file or a database URL (PostgreSQL between machines);
- study: opening a study, created or loaded, refused where tuned on other options;
- workers: the worker processes of one command, Ctrl-C; worker: one of them, its trials;
- report: the best settings scored on the held-out starts, <study>.json and .md;
- run: tune() -> TuneResult.
"""

from lab.tuning.run import tune, TuneResult

__all__ = ['tune', 'TuneResult']
