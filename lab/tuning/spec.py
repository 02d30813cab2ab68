"""What defines a study: the law, the settings held fixed or added to the search, the
objective, the penalty, the tuning starts, the swing bound and the run length; its default name,
and the options a study records so that a resume cannot mix two definitions."""

import dataclasses
import re

from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl.control.registry import law_class
from tsr_koopman_ctrl.control.settings import parse_value
from tsr_koopman_ctrl.model import LiftedModel
from lab.tuning.scoring import OBJECTIVES, TUNING_STARTS
from lab.tuning.space import searchable

#: Options a study keeps from its first command -> the value of a study that never recorded
#: one (studies from before --penalty and --starts were flat and tuned on the comparison
#: starts; every study recorded its objective).
RECORDED = {'objective': None, 'penalty': 'flat', 'starts': 'comparison'}


@dataclasses.dataclass(frozen=True)
class StudySpec:
    """One study's definition; `fix`: 'SETTING=VALUE' texts as given (they name the study),
    `also`: settings searched only when asked, `name`: the study's name where not the default
    one."""
    law: str
    fix: tuple = ()
    also: tuple = ()
    objective: str = 'settle'
    penalty: str = 'flat'
    starts: str = 'comparison'
    swing_max: float = 0.8
    steps: int = 2000
    name: str = None

    @property
    def study_name(self):
        if self.name:
            return self.name
        # A fixed value may be a path ('model=models/x'): only safe characters go into names.
        fixed = ''.join('_' + re.sub(r'[^A-Za-z0-9.-]+', '-', text.replace('=', '-'))
                        for text in self.fix)
        fixed += ''.join(f'_with-{name}' for name in self.also)
        objective = '' if self.objective == 'settle' else '_' + self.objective
        penalty = '' if self.penalty == 'flat' else '_' + self.penalty
        starts = '' if self.starts == 'comparison' else f'_{self.starts}-starts'
        return f'{self.law}{fixed}{objective}{penalty}{starts}_swing{self.swing_max:g}'

    @property
    def graded(self):
        return self.penalty == 'graded'

    @property
    def tuning_starts(self):
        return TUNING_STARTS[self.starts]

    def check(self):
        """ValueError where an option names no law, objective, penalty or start set."""
        if self.law not in CONTROLLERS:
            raise ValueError(f'no law {self.law!r}; laws: {sorted(CONTROLLERS)}')
        for option, choices in (('objective', OBJECTIVES), ('penalty', ('flat', 'graded')),
                                ('starts', TUNING_STARTS)):
            if getattr(self, option) not in choices:
                raise ValueError(f'--{option} {getattr(self, option)}: not one of '
                                 f'{sorted(choices)}')


def fixed_settings(spec):
    """{setting: value} of the spec's `fix` texts, checked against the law's settings, and the
    `also` names checked: ValueError in one line."""
    settings = law_class(spec.law).Settings
    pairs = [text.split('=', 1) for text in spec.fix]
    if any(len(pair) != 2 for pair in pairs):
        raise ValueError(f'--fix takes SETTING=VALUE, got {list(spec.fix)}')
    fixed = {name: parse_value(settings, name, value) for name, value in pairs}
    # Out of range, not a choice, the wrong length, a model that does not load: one line now
    # rather than 60 trials that all score the penalty.
    settings(**fixed)
    if 'model' in fixed:
        LiftedModel.load(fixed['model'])
    for name in spec.also:
        if name not in searchable(spec.law):
            raise ValueError(f'--also {name}: {spec.law} has no such searchable setting; '
                             f'searchable: {sorted(searchable(spec.law))}')
    return fixed
