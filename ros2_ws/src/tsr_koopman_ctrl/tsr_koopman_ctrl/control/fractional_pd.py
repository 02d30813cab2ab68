"""Fractional-order tension law (Sun 2014 type, PD^alpha), gains documented here."""

import dataclasses
from typing import ClassVar

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.law import Law, planar_state
from tsr_koopman_ctrl.control.settings import LawSettings, setting


@dataclasses.dataclass(frozen=True)
class FractionalPdSettings(LawSettings):
    law: ClassVar[str] = 'fractional_pd'
    # Tuned for the frontier ratio: lab/tune.py --objective worst-ratio, 100 trials, swing
    # <= 0.8 rad (docs/tuning.md); tuned for the mean settle time: config/tuned_settle.yaml;
    # before tuning alpha = 0.9 and the linear LQR's gains for Q = I, R = 1 (config/untuned.yaml).
    alpha: float = setting(0.7569, 'order of the fractional derivative', low=0.01, high=1.5,
                           tune=(0.5, 1.2, 'linear'))
    gains: tuple = setting((6.776, 3.921, -11.07, -7.908),
                           'gains (k_theta, d_theta, k_l, d_l) on theta, D^alpha theta, l - 1, '
                           'D^alpha (l - 1)',
                           tune=[(0.0, 10.0, 'linear'), (-5.0, 5.0, 'linear'),
                                 (-20.0, 0.0, 'linear'), (-20.0, 0.0, 'linear')])
    memory: int = setting(200, 'samples of the Grunwald-Letnikov sum', low=1, high=100_000)


class FractionalOrderPd(Law):
    """u = 3 - (k_theta theta + k_l (l - 1)) - D^alpha (d_theta theta + d_l (l - 1)).

    D^alpha by Grunwald-Letnikov over the last `memory` samples of period h (history before the
    first sample taken equal to it; samples a real-time loop dropped, `elapsed`, interpolated
    between the ones on either side, so that the sum keeps its time base). With alpha = 1 this
    is the linearised LQR law with the rates replaced by differenced positions; the untuned
    gains are that law's (Q = I, R = 1) and alpha = 0.9 adds the fractional operator's memory.
    """

    name = 'fractional_pd'
    Settings = FractionalPdSettings

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        s = self.settings
        self.k_theta, self.d_theta, self.k_l, self.d_l = s.gains
        weights = [1.0]
        for j in range(1, s.memory + 1):
            weights.append(weights[-1] * (1.0 - (s.alpha + 1.0) / j))
        self.weights = np.array(weights) / self.h ** s.alpha
        self.reset()

    def reset(self):
        super().reset()
        self.history = None
        self.missed = 0

    def elapsed(self, steps):
        # The history is a sampled signal: the samples between are filled in at the next
        # compute, once the sample after them is known.
        if self.history is not None:
            self.missed += int(steps) - 1

    def compute(self, x):
        x = planar_state(x)
        signal = self.d_theta * x[dynamics.THETA] + self.d_l * x[dynamics.LENGTH_OFFSET]
        if self.history is None:
            self.history = np.full(len(self.weights), signal)
        last, gap = self.history[0], self.missed + 1
        self.missed = 0
        shift = min(gap, len(self.history))
        self.history = np.roll(self.history, shift)
        # Newest first: signal, then the dropped samples back towards the last one seen.
        self.history[:shift] = (signal + (last - signal) * np.arange(gap) / gap)[:shift]
        derivative = float(self.weights @ self.history)
        proportional = self.k_theta * x[dynamics.THETA] + self.k_l * x[dynamics.LENGTH_OFFSET]
        return dynamics.EQUILIBRIUM_TENSION - proportional - derivative
