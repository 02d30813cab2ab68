"""One control step, shared by the controller node and the ROS-free `closed_loop`: the law's
tension for a measured state, the excitation added, the clamp, and the law told what was sent.

    step = ControlStep(make_controller('koopman_mpc'), TensionLimiter(5.0))
    step.reset()
    result = step(x)      # result.tension (clamped, dimensionless), .outcome, .compute_seconds

A state that is not finite, or that no TSR can be in (`tsr_sim.dynamics.plausible`), is refused
before the law sees it: no tension, and the law and its observer never remember it.
"""

from dataclasses import dataclass
import enum
import math
import time

import numpy as np
from tsr_sim import dynamics


class Outcome(enum.IntEnum):
    """What a step did; the values are those of tsr_msgs/ControllerStatus."""

    OK = 0
    CLAMPED = 1             # the tension was outside [0, u_max] and was clamped
    SOLVER_FALLBACK = 2     # the law's optimiser failed and it fell back
    NON_FINITE_STATE = 3    # the state was not finite: refused, no command
    NON_FINITE_OUTPUT = 5   # the law gave a non-finite tension: no command
    REFUSED_STATE = 6       # the state is no TSR state (`dynamics.plausible`): no command


@dataclass
class StepResult:
    tension: float          # the command, dimensionless and clamped (NaN when none)
    excitation: float       # what the excitation added before the clamp
    outcome: Outcome
    compute_seconds: float  # the law's compute() alone, wall clock


class ControlStep:
    """A law with what every loop does around it (module docstring). `limiter` is the one
    output clamp; `excitation` (control.excitation.Excitation) may be None."""

    def __init__(self, law, limiter, excitation=None):
        self.law, self.limiter, self.excitation = law, limiter, excitation

    def reset(self):
        """Before a new run: the law (and its observer) and the excitation forget the past."""
        self.law.reset()
        if self.excitation is not None:
            self.excitation.reset()

    def resume(self):
        """After a pause in the same run: the law resumes (`Law.resume`: warm, its
        disturbance estimate kept); the excitation goes on where it was."""
        self.law.resume()

    @staticmethod
    def check(x):
        """None for a state the law may see, else why it is refused (NON_FINITE_STATE,
        REFUSED_STATE)."""
        x = np.asarray(x, dtype=float)
        if not np.all(np.isfinite(x)):
            return Outcome.NON_FINITE_STATE
        if x.ndim != 1 or not dynamics.plausible(x[:dynamics.PLANAR_DIM]):
            return Outcome.REFUSED_STATE
        return None

    def __call__(self, x, elapsed=1):
        """The step for state x, measured `elapsed` samples after the last one (a real-time
        loop drops states it could not answer in time: the law catches up, `Law.elapsed`)."""
        refused = self.check(x)
        if refused is not None:
            return StepResult(math.nan, 0.0, refused, 0.0)
        if elapsed > 1:
            self.law.elapsed(elapsed)
        fallbacks, clamped = self.law.fallbacks, self.limiter.clamped
        start = time.perf_counter()
        u = self.law.compute(x)
        elapsed = time.perf_counter() - start
        if not math.isfinite(u):
            return StepResult(math.nan, 0.0, Outcome.NON_FINITE_OUTPUT, elapsed)
        added = (self.excitation.next() if self.excitation is not None
                 and self.excitation.active else 0.0)
        command = self.limiter(u + added)
        self.law.applied(command)
        outcome = (Outcome.SOLVER_FALLBACK if self.law.fallbacks > fallbacks
                   else Outcome.CLAMPED if self.limiter.clamped > clamped else Outcome.OK)
        return StepResult(command, added, outcome, elapsed)
