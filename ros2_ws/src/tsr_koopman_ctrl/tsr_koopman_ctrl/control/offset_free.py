"""Offset-free control: any law wrapped with a disturbance observer (`observer.py`).

The observer (an extended Kalman filter on the planar state and one input disturbance d) gives
the law a filtered state; the law returns the tension it wants the plant to feel; the command is
the observer's phi^-1 of it (u / d for a gain, u - d for an additive disturbance). With an input
disturbance the steady-state target of the offset-free formulation (Pannocchia & Rawlings 2003;
Maeder, Borrelli & Morari 2009) is the nominal one, x = 0 with u = 3 felt, so the target
calculation reduces to that inversion and no constant gain or bias the observer converges to
leaves an offset. A law with tension bounds of its own (koopman_mpc, the NMPC) gets them moved to
the felt tensions the actuator can reach, [phi(0), phi(u_max)], so its constraints stay the real
actuator's. The observer is told the clamped command that was sent (anti-windup for free).

Why not an integrator on l - 1 for the linear laws: measured (docs/robustness.md), the
observer-wrapped linear LQR is as fast as the LQR on the nominal plant and settles in every
disturbed case, while the best integrator (band 0.2, weight 3) cost up to 1.26x and a larger
swing.
"""

import dataclasses
import math
from typing import ClassVar

import numpy as np

from tsr_koopman_ctrl.control.law import planar_state, WARM_UP_STATES, Wrapper
from tsr_koopman_ctrl.control.observer import (DisturbanceObserver, koopman_predictor,
                                               physics_predictor)
from tsr_koopman_ctrl.control.settings import build, LawSettings, setting


@dataclasses.dataclass(frozen=True)
class ObserverSettings(LawSettings):
    law: ClassVar[str] = 'observer'
    disturbance: str = setting('gain', "offset-free control: the input disturbance estimated "
                               "('gain': actuator gain and mass error; 'additive': a tension "
                               "bias) and corrected; 'none': the bare law",
                               choices=('none', 'gain', 'additive'))
    predictor: str = setting('auto', "the filter's one-step model: 'model' (the law's learned "
                             "model: data-driven), 'physics' (the nominal equations), 'auto' "
                             "(the law's model if it has one, else physics)",
                             choices=('auto', 'model', 'physics'))
    sensor_std: float = setting(1e-3, 'measurement noise std per component (dimensionless)',
                                low=1e-9, high=1.0)
    rate_noise_std: float = setting(1e-4, "model error per step on theta' and l'", low=0.0,
                                    high=1.0)
    position_noise_std: float = setting(1e-6, 'model error per step on theta and l - 1',
                                        low=0.0, high=1.0)
    disturbance_walk_std: float = setting(3e-3, 'how fast the disturbance may move, per step',
                                          low=0.0, high=1.0)
    initial_disturbance_std: float = setting(0.2, 'how far from nominal it may start', low=0.0,
                                             high=10.0)
    actuator_lag: float = setting(0.0, 'actuator time constant the filter models [tau] (0: '
                                  'none; needed when the real lag exceeds ~0.1 tau)', low=0.0,
                                  high=100.0)
    filtered_state: bool = setting(True, 'give the law the filtered state (else the raw '
                                   'measurement; the disturbance is corrected either way)')


class OffsetFree(Wrapper):
    """`law` wrapped with a disturbance observer; a law itself (its name, settings, model, h,
    u_max and fallbacks are the wrapped law's)."""

    def __init__(self, law, settings=None, **overrides):
        super().__init__(law)
        self.observer_settings = s = build(ObserverSettings, settings, overrides)
        if s.predictor == 'model' and law.model is None:
            raise ValueError(f'observer.predictor model: {law.name} has no model')
        use_model = s.predictor == 'model' or (s.predictor == 'auto' and law.model is not None)
        predictor = (koopman_predictor(law.model) if use_model
                     else physics_predictor(h=law.h))
        self.observer = DisturbanceObserver(
            predictor, disturbance=s.disturbance, sensor_std=s.sensor_std,
            rate_noise_std=s.rate_noise_std, position_noise_std=s.position_noise_std,
            disturbance_walk_std=s.disturbance_walk_std,
            initial_disturbance_std=s.initial_disturbance_std, actuator_lag_tau=s.actuator_lag,
            h=law.h)
        self.reset()

    def reset(self):
        self.law.reset()
        self.observer.reset()
        self.last_command = None

    @property
    def disturbance(self):
        return self.observer.disturbance

    def compute(self, x):
        measured = planar_state(x)
        estimate = self.observer.update(measured, self.last_command)
        # A filter gone non-finite (x_hat or d; a_hat is NaN by design until the first
        # command): no tension, which the node reports as NON_FINITE_OUTPUT, not an exception.
        if not (np.all(np.isfinite(estimate)) and np.isfinite(self.observer.disturbance)):
            return float('nan')
        # A law with bounds of its own plans within the felt tensions the actuator can reach.
        low = max(self.observer.applied(0.0), 0.0)
        self.law.bound_tension(low, max(self.observer.applied(self.law.u_max), low + 1e-6))
        felt = self.law.compute(estimate if self.observer_settings.filtered_state else measured)
        if not math.isfinite(felt):
            return math.nan      # (no command: the last one sent stays the observer's)
        command = min(max(self.observer.command_for(felt), 0.0), self.law.u_max)
        self.last_command = command   # the observer must know the clamped command
        return command

    def warm_up(self):
        """The law's own warm-up (its paths, states and cold starts), then a few steps of one
        state through the observer: what the wrapper adds is built, the law's work not done
        twice."""
        self.law.warm_up()
        self.reset()
        for _ in range(3):
            self.applied(self.compute(WARM_UP_STATES[0]))
        self.reset()

    def elapsed(self, steps):
        """The observer predicts across the samples dropped, under the command held."""
        if self.last_command is not None:
            self.observer.coast(self.last_command, steps - 1)
        self.law.elapsed(steps)

    def resume(self):
        """The law resumes (`Law.resume`); the observer keeps its disturbance estimate and
        goes on from the last command sent, or starts again from the next measurement if that
        lies where it did not predict (`DisturbanceObserver.resume`)."""
        self.law.resume()
        self.observer.resume()

    def observe(self, x):
        """The observer keeps up with the measurement; the law drops its plan."""
        self.observer.update(planar_state(x), self.last_command)
        self.law.observe(x)

    def applied(self, command):
        """Tell the observer the command actually sent, and the law the tension it makes the
        plant feel, when it is not the one `compute` returned (an excitation was added, a
        clamp changed it, or another law flew: the supervisor)."""
        if command != self.last_command:
            self.law.applied(self.observer.applied(command))
        self.last_command = float(command)

    def felt(self, command):
        return float(self.observer.applied(command))

    def command_for(self, felt):
        return float(self.observer.command_for(felt))

    def felt_least(self, command, sigmas):
        o = self.observer
        weakest = o.disturbance - sigmas * o.spread
        return float(min(o.applied(command), o.applied(command, weakest)))

    def hand_over(self, reason):
        return None       # (a law under the observer has no fallback of its own)

    def residual(self):
        """The observer's innovation: the measurement less its model's one-step prediction
        (the disturbance estimate included)."""
        return self.observer.innovation

    def diagnostics(self):
        return {**self.law.diagnostics(), 'disturbance_estimate': self.observer.disturbance,
                'disturbance': self.observer_settings.disturbance}
