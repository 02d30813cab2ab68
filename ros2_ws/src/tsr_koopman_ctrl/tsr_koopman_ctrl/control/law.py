"""The interface every tension law implements, ROS-free: what a law offers is declared here,
never probed.

A law works in the paper's dimensionless variables: `compute(x)` takes the measured planar state
[theta, theta', l - 1, l'] (a 3-D state is cut to its planar part) and returns the tension u; the
loop's one step (`control.step.ControlStep`) adds the excitation, clamps it with
`TensionLimiter` and tells the law what was sent (`applied`). `reset()` forgets the past (before
a new run). Settings come from the law's `Settings` class (`settings.py`); the sample period h
and the tension limit u_max are the loop's, not the law's, so they are separate. A law may plan
with a learned model (`model`), bound the tension it plans with (`bound_tension`), count the
steps its optimiser failed (`fallbacks`), show the states its plan predicts (`prediction`) and
how far its model's last one-step prediction missed (`residual`), which the runtime-assurance
supervisor judges it by (`supervisor.py`), hand its plan to another law on the same grid
(`guess`, `start_from`: the supervisor's learned law starts from the fallback's plan instead of
a cold start), and report on itself (`diagnostics`).
"""

import math

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.settings import build, LawSettings


def planar_state(x):
    """The planar part [theta, theta', l - 1, l'] of a measured state, which must have 4
    (planar) or 6 (3-D) finite components: ValueError otherwise, so that a wrong vector never
    yields a plausible tension and a NaN never reaches a law's or an observer's memory."""
    x = np.asarray(x, dtype=float)
    if x.ndim != 1:
        raise ValueError(f'a TSR state is one vector of {dynamics.PLANAR_DIM} or '
                         f'{dynamics.SPATIAL_DIM} components, got shape {x.shape}')
    dynamics.check_state_dim(x.shape[0])
    # One sum is the fast test; only a sum that overflowed needs the component-wise one.
    if not math.isfinite(x.sum()) and not np.isfinite(x).all():
        raise ValueError(f'the state {x.tolist()} is not finite: no tension for it')
    return x[:dynamics.PLANAR_DIM]


#: States a law is warmed up from (`Law.warm_up`): the paper's start, mid-deployment and the
#: deployed equilibrium.
WARM_UP_STATES = (dynamics.PAPER_INITIAL_STATE, np.array([-0.4, -0.6, -0.7, 0.5]),
                  dynamics.equilibrium_state())


class Law:
    name = ''
    Settings = LawSettings
    #: The learned model the law plans with (`model.LiftedModel`), or None.
    model = None
    #: A learned law the predictive safety filter wraps by default (`safety_filter.backup`
    #: 'auto'): the learned NMPC. The linear Koopman laws opt in by setting the backup.
    filtered = False
    #: Under the runtime-assurance supervisor (`supervisor.py`): the law that flew the last
    #: step ('learned' or 'fallback'), why the monitor distrusts the learned law ('' when it
    #: does not) and how often the flying law changed; '', '' and 0 for a law flown alone.
    flying = ''
    monitor = ''
    switches = 0
    #: Under the predictive safety filter (`safety_filter.py`): how the last step was flown
    #: (`safety_filter.CERTIFIED`, ...), the tension the filtered law asked
    #: for then, the steps where the command flown differed from the one asked for and the sum
    #: of |flown - asked|; '', NaN, 0 and 0 for a law flown unfiltered.
    certificate = ''
    requested = math.nan
    corrections = 0
    correction_sum = 0.0

    def __init__(self, settings=None, *, h=dynamics.PAPER_STEP, u_max=dynamics.TENSION_LIMIT,
                 **overrides):
        self.settings = build(self.Settings, settings, overrides)
        if not (h > 0.0 and u_max > 0.0):
            raise ValueError(f'h and u_max must be > 0, got {h}, {u_max}')
        self.h, self.u_max = float(h), float(u_max)
        #: Steps where an optimiser failed and the law fell back (counted, reported on the wire).
        self.fallbacks = 0

    def reset(self):
        self.fallbacks = 0

    def resume(self):
        """After a pause in the same run (the controller deactivated and activated again;
        the plant may have been held by its reel hold meanwhile, over samples the law does not
        see): a resume is not a reset. A law with a plan keeps it as the next step's warm
        start (unless the state measured then shows the plant moved off it), an observer its
        disturbance estimate, a monitor its verdict. Laws whose only memory is of the last
        samples: `reset` (the default), they start where the plant is."""
        self.reset()

    def warm_up(self):
        """Compute from a few representative states (WARM_UP_STATES) and forget them: what is
        built or cached on first use (compiled functions, imports) is built now, so that the
        first command of a run is as fast as the rest."""
        for x in WARM_UP_STATES:
            self.reset()
            for _ in range(3):
                self.applied(self.compute(x))
        self.reset()

    def compute(self, x):
        """The tension for the measured state x (`planar_state` checks it)."""
        raise NotImplementedError

    def limit_tension(self, u_max):
        """The loop's tension limit is now u_max (a live `max_tension`): the law plans and
        clamps within it from its next step. A law wrapping laws passes it on."""
        if not (math.isfinite(u_max) and u_max > 0.0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max}')
        self.u_max = float(u_max)

    def bound_tension(self, low, high):
        """The tensions the law may plan with, when they are not [0, u_max] (an offset-free
        wrapper gives the felt range the actuator can reach). Laws without bounds of their own
        ignore it: the clamp after them holds the limit."""

    def elapsed(self, steps):
        """The next state comes `steps` > 1 samples after the last one the law computed for: a
        real-time loop dropped the states between, over which the last command was held. A
        law with memory of time (a plan, an observer) catches up; the others ignore it."""

    def observe(self, x):
        """The law is not asked for a tension this step but sees the state x (the supervisor's
        untrusted learned law, resting): an observer keeps up with it, a plan is dropped (the
        next `compute` starts afresh); the others ignore it."""

    def applied(self, command):
        """The command actually sent after `compute` (an excitation added, a clamp, or another
        law's: the supervisor's fallback flew, or the learned law in its shadow): a law with
        memory of what was flown (an observer, a plan's rate term, an actuator model) takes
        it from here; the others ignore it."""

    def on_trial(self, trial):
        """`trial` True: from this step on another law's commands fly and this law's are only
        judged (the supervisor's learned law while its fallback flies), False: its own fly. A
        law whose failed step recovers at a cost (the NMPC's cold start) answers NaN on trial
        instead (no command, and a fallback counted), so that judging it never stretches the
        loop's step; the others ignore it."""

    def hand_over(self, reason):
        """The safety filter refused this step's tension (`reason`): a law with a verified
        fallback of its own (the supervisor) hands the plant to it from here and returns the
        fallback's tension for this step if it planned one, else None (the filter then flies
        its own backup this step). Laws without one: None."""
        return None

    def swing_bound(self):
        """The bound on |theta| the law plans within [rad] (its `theta_max` setting), inf for
        a law without one. The supervisor judges plans and the safety filter certifies
        backups against it."""
        return math.inf

    def felt(self, command):
        """The tension the plant feels for `command` by what the law knows of the actuator
        (the offset-free observer's disturbance estimate); the command itself without one."""
        return float(command)

    def command_for(self, felt):
        """The command that makes the plant feel `felt` (the inverse of `felt`)."""
        return float(felt)

    def felt_least(self, command, sigmas):
        """The least tension the plant may feel for `command`: the disturbance estimate taken
        `sigmas` standard deviations of its uncertainty toward less tension (an actuator not
        yet seen pulling is known no better than the observer's prior); `felt` without an
        observer."""
        return self.felt(command)

    def prediction(self):
        """The states the law's plan predicts from the last state it computed for (N + 1, n),
        or None for a law without a plan. The supervisor checks the plan's bounds on it."""
        return None

    def guess(self):
        """The plan made at the last `compute`, for another law on the same grid to start
        from: (tensions (N,), node states (N + 1, n)), or None for a law without a plan."""
        return None

    def start_from(self, guess):
        """Offered, before this step's `compute`, a plan made for this step's state by another
        law on the same grid (its `guess`): a law that would otherwise start cold this step (no
        plan of its own) starts from it; the others ignore it."""

    def prediction_times(self):
        """When the states of `prediction` lie, in tau after the last state (N + 1,), or None
        for a law without a plan."""
        return None

    def residual(self):
        """How far the state of the last `compute` lies from the law's one-step prediction of
        it (its model's, from the state before and the tension felt): (n,), or None for a law
        without a model of the plant or before its second step."""
        return None

    def diagnostics(self):
        """{name: value} a law reports about itself on /diagnostics (e.g. an estimate)."""
        return {}


class Wrapper(Law):
    """A law around another (`law`): the offset-free wrapper, the safety filter. Its name,
    settings, model, h and u_max are the wrapped law's, and what it does not change it
    forwards: the plan and its times, the plan offered and handed on, the residual, the swing
    bound, the actuator's mapping, the hand-over and the fallback count."""

    def __init__(self, law):
        self.law = law
        self.name, self.Settings, self.settings = law.name, law.Settings, law.settings
        self.h, self.u_max, self.model = law.h, law.u_max, law.model

    @property
    def fallbacks(self):
        return self.law.fallbacks

    def limit_tension(self, u_max):
        super().limit_tension(u_max)
        self.law.limit_tension(u_max)

    def swing_bound(self):
        return self.law.swing_bound()

    def felt(self, command):
        return self.law.felt(command)

    def command_for(self, felt):
        return self.law.command_for(felt)

    def felt_least(self, command, sigmas):
        return self.law.felt_least(command, sigmas)

    def on_trial(self, trial):
        self.law.on_trial(trial)

    def hand_over(self, reason):
        return self.law.hand_over(reason)

    def prediction(self):
        return self.law.prediction()

    def prediction_times(self):
        return self.law.prediction_times()

    def guess(self):
        return self.law.guess()

    def start_from(self, guess):
        self.law.start_from(guess)

    def residual(self):
        return self.law.residual()

    def diagnostics(self):
        return self.law.diagnostics()
