"""Bounded excitation added to a law's tension, so a deployment bag is informative for
identification (off by default). ROS-free and seeded: the same seed gives the same sequence."""

import dataclasses
import math
from typing import ClassVar

import numpy as np

from tsr_koopman_ctrl.control.settings import LawSettings, setting


@dataclasses.dataclass(frozen=True)
class ExcitationSettings(LawSettings):
    law: ClassVar[str] = 'excitation'
    kind: str = setting('none', "'none', 'prbs' (a random +-amplitude level held for hold "
                        "steps) or 'noise' (white noise through a first-order filter with a "
                        "time constant of hold steps, clipped to +-amplitude)",
                        choices=('none', 'prbs', 'noise'))
    amplitude: float = setting(0.3, 'largest excitation, dimensionless tension u', low=0.0,
                               high=5.0)
    hold: int = setting(20, 'steps a PRBS level is held; the noise filter time constant in '
                        'steps', low=1, high=100_000)
    seed: int = setting(0, 'random seed', low=0, high=2 ** 31 - 1)


class Excitation:
    """`next()` gives the excitation for the next step, |value| <= amplitude."""

    def __init__(self, settings=None, **overrides):
        from tsr_koopman_ctrl.control.settings import build
        self.settings = build(ExcitationSettings, settings, overrides)
        self.reset()

    @property
    def active(self):
        return self.settings.kind != 'none' and self.settings.amplitude > 0.0

    def reset(self):
        self.rng = np.random.default_rng(self.settings.seed)
        self.step, self.level, self.filtered = 0, 0.0, 0.0

    def next(self):
        s = self.settings
        if not self.active:
            return 0.0
        if s.kind == 'prbs':
            if self.step % s.hold == 0:
                self.level = s.amplitude * (1.0 if self.rng.random() < 0.5 else -1.0)
            value = self.level
        else:
            # Unit-variance filtered noise: the first-order filter's gain keeps the variance 1.
            pole = math.exp(-1.0 / s.hold)
            self.filtered = pole * self.filtered + math.sqrt(1.0 - pole ** 2) * self.rng.normal()
            value = min(max(s.amplitude * self.filtered / 2.0, -s.amplitude), s.amplitude)
        self.step += 1
        return value
