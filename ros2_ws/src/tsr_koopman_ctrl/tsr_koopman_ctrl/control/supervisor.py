"""Runtime assurance: a learned law flown under a monitor, with a verified law to take over.

Simplex architecture (Sha 2001; the pattern of ros2_control's `fallback_controllers`): every
step the monitor judges the learned law from what it already knows, and the step is flown by
the learned law while it is trusted, else by the fallback, a law shown to hold the plant from
the states where it takes over (docs/supervisor.md has the region, lab/fallback_region.py
measures it). The learned law keeps computing while the fallback flies (told the tension
flown) and takes back, with hysteresis, once it has been trusted for `takeback_steps` steps
in a row; when it faults while the fallback flies, it rests for `takeback_steps` steps (it sees
the states, its observer keeps up, it plans nothing: a lost learned law would fail every
step) and then starts afresh on probation, from the plan the fallback made for that state (one
RTI step: `Law.start_from`), not from a cold start. Judged while the fallback flies, it is on
trial (`Law.on_trial`): a failed step answers no command (distrusted at once) instead of the
cold start that recovers it while it flies, so that judging it never stretches the loop's
step (in the 100 Hz timed loop such cold starts took 50-70 ms). A learned law distrusted
again within its probation (the wait it just served, after taking back) waits twice as long
the next time, up to `takeback_backoff` times `takeback_steps`, and back to `takeback_steps`
once it has flown a whole probation trusted: a model that is wrong near the target would
otherwise take back and lose the plant again every few tens of steps, and the plant would
never settle. The fallback computes every step too (`shadow`), so it takes over warm: its
plan is the one it would be flying.

What the monitor watches (each a reason on /diagnostics and in the bag):

- `fallback`, `bound`: the learned law faulted on `fault_count` of the last `fault_window`
  steps, a fault being a step where its optimiser fell back or its plan (a law that has one:
  `Law.prediction`) breaks its swing bound by more than `bound_tolerance` within
  `bound_horizon` (the plan beyond is planned again before it flies); a non-finite
  tension, plan or prediction is `fallback` at once. One fault is no
  reason: a single failed QP at a bang-bang switch is part of a nominal deployment; a learned
  model that cannot keep its own plan within the bound faults step after step;
- `envelope`: the state lies outside the envelope the model was trained on (the model file's
  `envelope`, widened by `envelope_margin` of its width);
- `prediction`: the model's one-step prediction from the last state and the tension felt
  missed the state now by more than `prediction_threshold` (any component, dimensionless).

The supervisor is a law itself (its name, settings and model are the learned law's), so the
offset-free wrapper, the control step, the node and `closed_loop` take it as they take a law.
"""

import dataclasses
from typing import ClassVar

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.law import Law, planar_state
from tsr_koopman_ctrl.control.settings import build, LawSettings, setting

#: Which law flew a step (ControllerStatus.flying, /diagnostics).
LEARNED, FALLBACK = 'learned', 'fallback'
#: Why the monitor distrusts the learned law (ControllerStatus.monitor; '' when it trusts it).
REASONS = ('fallback', 'bound', 'envelope', 'prediction', 'certificate')


@dataclasses.dataclass(frozen=True)
class SupervisorSettings(LawSettings):
    law: ClassVar[str] = 'supervisor'
    fallback: str = setting('physics_nmpc', "the verified law that takes over: "
                            "'physics_nmpc' (the NMPC on the exact equations, the learned "
                            "law's cost and bounds); 'none': the learned law unsupervised",
                            choices=('none', 'physics_nmpc'))
    fault_count: int = setting(2, 'faults of the learned law (its optimiser fell back, or its '
                               'plan breaks the swing bound) within fault_window steps that '
                               'make it untrusted', low=1, high=1000)
    fault_window: int = setting(2, 'steps over which faults are counted', low=1, high=100000)
    bound_tolerance: float = setting(0.005, "how far the learned plan's swing may pass the "
                                     'swing bound before the step is a fault [rad]', low=0.0,
                                     high=10.0)
    bound_horizon: float = setting(1.0, "how far ahead the learned plan's swing is judged "
                                   'against the bound [tau]: off-nominal, the far end of a '
                                   'plan passes it where the run never does (a needless '
                                   'switch); 0.5 missed a tumble under theta_max 0.4',
                                   low=0.0, high=100.0)
    envelope_margin: float = setting(0.1, "the model's training envelope widened by this "
                                     'fraction of its width on each side', low=0.0, high=10.0)
    prediction_threshold: float = setting(0.2, "largest miss of the model's one-step "
                                          'prediction, any component (dimensionless)',
                                          low=0.0, high=1e6)
    takeback_steps: int = setting(20, 'steps in a row the learned law must be trusted before '
                                  'it takes back from the fallback', low=1, high=10 ** 7)
    takeback_backoff: int = setting(16, 'a learned law distrusted again within its probation '
                                    'after taking back waits twice as long the next time, up '
                                    'to this many times takeback_steps (1: always '
                                    'takeback_steps)', low=1, high=10 ** 6)
    shadow: str = setting('auto', "when the fallback plans beside the learned law, so that it "
                          "takes over warm: 'armed' (for arm_steps steps after each fault of "
                          "the learned law), 'always', 'never' (it starts cold when it "
                          "takes over), or 'auto': always under the safety filter (it may "
                          'hand over at any step), else armed; its observer keeps up every '
                          'step', choices=('auto', 'armed', 'always', 'never'))
    arm_steps: int = setting(100, 'steps the fallback stays armed after a fault of the learned '
                             'law', low=1, high=10 ** 7)


class Supervisor(Law):
    """`learned` flown under the monitor, `fallback` taking over (module docstring). Each is a
    law as it would be deployed alone (offset-free, with its own observer), so the fallback
    flies exactly as it was verified. `filtered`: a safety filter flies it (`shadow` 'auto'
    resolves to 'always')."""

    def __init__(self, learned, fallback, settings=None, filtered=False, **overrides):
        self.learned, self.fallback = learned, fallback
        self.name, self.Settings, self.settings = learned.name, learned.Settings, learned.settings
        self.h, self.u_max, self.model = learned.h, learned.u_max, learned.model
        self.supervisor_settings = build(SupervisorSettings, settings, overrides)
        if self.supervisor_settings.shadow == 'auto':
            # A filter hands over at any step: the fallback then takes over warm from its own
            # plan, as the verified law alone flies (cold, or from the filter's plan, its
            # plans drifted off the verified law's and lost robots it held).
            self.supervisor_settings = dataclasses.replace(
                self.supervisor_settings, shadow='always' if filtered else 'armed')
        if self.supervisor_settings.fault_count > self.supervisor_settings.fault_window:
            raise ValueError('supervisor.fault_count must be <= supervisor.fault_window (more '
                             'faults than steps counted would never distrust the law), got '
                             f'{self.supervisor_settings.fault_count} > '
                             f'{self.supervisor_settings.fault_window}')
        self.envelope = None
        if self.model is not None and self.model.envelope is not None:
            low, high = (np.asarray(v, dtype=float) for v in self.model.envelope)
            widen = self.supervisor_settings.envelope_margin * (high - low)
            self.envelope = (low - widen, high + widen)
        self.theta_bound = learned.swing_bound()
        self.reset()

    def reset(self):
        self.learned.reset()
        self.fallback.reset()
        self.flying = LEARNED
        self.monitor = ''            # why the monitor distrusts the learned law now ('': not)
        self.switches = 0
        self.trusted_steps = 0
        self.faults = []             # (step, reason) of the learned law's recent faults
        self.resting = 0             # steps the untrusted learned law still rests
        self.takeback = self.supervisor_settings.takeback_steps   # the hysteresis now
        self.flown = None            # steps the learned law has flown since it took back
        self.armed = 0               # steps the fallback still plans in the shadow
        self.steps = 0
        self.planned = None          # the fallback's (tension, fell back) this step, or None
        self.fallbacks = 0           # steps where the law that flew fell back
        self.reasons = {reason: 0 for reason in REASONS}

    def bound_tension(self, low, high):
        self.learned.bound_tension(low, high)
        self.fallback.bound_tension(low, high)

    def compute(self, x):
        x = planar_state(x)
        s = self.supervisor_settings
        # The fallback plans whenever it flies or may soon (armed); otherwise it only sees the
        # state, so that its observer keeps up.
        fallback = (self.run(self.fallback, x) if self.flying == FALLBACK or
                    s.shadow == 'always' or (s.shadow == 'armed' and self.armed) else None)
        if fallback is not None:
            # The learned law, if it has no plan this step (back from its rest), starts from
            # the fallback's: one RTI step, not a cold start
            self.learned.start_from(self.fallback.guess())
        learned = None
        if self.resting:
            self.resting -= 1
            self.learned.observe(x)
        else:
            # While the fallback flies the learned law is judged, not flown: a failed step
            # is its verdict, not a cold start that stretches the step (`Law.on_trial`)
            self.learned.on_trial(self.flying != LEARNED)
            learned = self.run(self.learned, x)
            self.monitor = self.judge(x, *learned)
            if self.monitor:
                self.reasons[self.monitor] += 1
                self.trusted_steps = 0
                if self.flying == LEARNED:
                    self.take_over()
                else:
                    self.resting = self.takeback
            else:
                self.trusted_steps += 1
                if self.flying == FALLBACK and self.trusted_steps >= self.takeback:
                    self.switch(LEARNED)
                    self.flown = 0
                elif self.flying == LEARNED and self.flown is not None:
                    self.flown += 1
                    if self.flown >= self.takeback:     # a whole probation trusted
                        self.takeback, self.flown = s.takeback_steps, None
        if fallback is None and (self.flying == FALLBACK or (s.shadow == 'armed'
                                                             and self.armed)):
            fallback = self.run(self.fallback, x)       # armed, or taking over, this step
        elif fallback is None:
            self.fallback.observe(x)
        self.armed = max(self.armed - 1, 0)
        tension, fell_back = learned if self.flying == LEARNED else fallback
        self.fallbacks += fell_back
        self.steps += 1
        self.planned = fallback     # this step's fallback tension, for `hand_over`
        return tension

    def hand_over(self, reason):
        """The safety filter refused the learned law's tension (`reason`, 'certificate'):
        the fallback flies from here, as after the monitor's distrust (the same hysteresis
        and backoff before the learned law takes back); its tension for this step if it
        planned this step (armed), else None."""
        if self.flying != LEARNED:
            return None
        self.monitor = reason
        self.reasons[reason] += 1
        self.take_over()
        self.armed = self.supervisor_settings.arm_steps
        return None if self.planned is None else self.planned[0]

    def take_over(self):
        """The fallback takes the plant from the learned law; lost again on probation, the
        learned law's next wait is longer."""
        s = self.supervisor_settings
        if self.flown is not None and self.flown < self.takeback:
            self.takeback = min(2 * self.takeback, s.takeback_backoff * s.takeback_steps)
        self.switch(FALLBACK)

    @staticmethod
    def run(law, x):
        """(law's tension for x, whether its optimiser fell back)."""
        before = law.fallbacks
        tension = law.compute(x)
        return tension, law.fallbacks > before

    def elapsed(self, steps):
        self.learned.elapsed(steps)
        self.fallback.elapsed(steps)

    def resume(self):
        """Both laws resume (`Law.resume`: plans kept as warm starts, disturbance estimates
        kept); the monitor's state stands: the law that flew flies on, a distrusted learned
        law still has to earn the plant back, its faults, rest and probation count on."""
        self.learned.resume()
        self.fallback.resume()

    def warm_up(self):
        """Both laws warmed (the fallback too, though it may not fly for a long time)."""
        self.learned.warm_up()
        self.fallback.warm_up()
        self.reset()

    def applied(self, command):
        """Both laws are told what was sent: the one that did not fly keeps up with it."""
        self.learned.applied(command)
        self.fallback.applied(command)

    def switch(self, flying):
        self.flying = flying
        self.switches += 1
        self.trusted_steps = 0
        if flying == FALLBACK:
            self.flown = None

    def judge(self, x, tension, fell_back):
        """'' if the learned law is trusted this step, else the reason it is not."""
        s = self.supervisor_settings
        plan = self.learned.prediction()
        missed = self.learned.residual()
        # A law gone non-finite (its observer, its plan) is distrusted at once: every
        # comparison below is False for NaN and would keep it trusted
        non_finite = not (np.isfinite(tension) and (plan is None or np.all(np.isfinite(plan)))
                          and (missed is None or np.all(np.isfinite(missed))))
        if fell_back or non_finite:
            self.faults.append((self.steps, 'fallback'))
        elif plan is not None and self.swing_ahead(plan) > self.theta_bound + s.bound_tolerance:
            self.faults.append((self.steps, 'bound'))
        if self.faults and self.faults[-1][0] == self.steps:
            self.armed = s.arm_steps + 1      # (this step's included)
        self.faults = [(k, why) for k, why in self.faults if k > self.steps - s.fault_window]
        if non_finite:
            return 'fallback'
        if len(self.faults) >= s.fault_count:
            return self.faults[-1][1]
        if self.envelope is not None and not (np.all(x >= self.envelope[0])
                                              and np.all(x <= self.envelope[1])):
            return 'envelope'
        if missed is not None and np.max(np.abs(missed)) > s.prediction_threshold:
            return 'prediction'
        return ''

    def swing_ahead(self, plan):
        """The largest |theta| of the learned plan within bound_horizon (all of it for a law
        that does not say when its states lie)."""
        times = self.learned.prediction_times()
        if times is not None:
            plan = plan[times <= self.supervisor_settings.bound_horizon + 1e-9]
        return float(np.abs(plan[:, dynamics.THETA]).max()) if len(plan) else 0.0

    def prediction_times(self):
        return (self.learned if self.flying == LEARNED else self.fallback).prediction_times()

    def prediction(self):
        return (self.learned if self.flying == LEARNED else self.fallback).prediction()

    def guess(self):
        return (self.learned if self.flying == LEARNED else self.fallback).guess()

    def start_from(self, guess):
        """Offered a plan for the law that flies next: after a hand-over with no plan of the
        fallback's this step (`shadow` armed or never) the safety filter offers its verified
        law's (cold, the fallback's poorer first plan lost the robot where the verified law
        alone held it)."""
        (self.learned if self.flying == LEARNED else self.fallback).start_from(guess)

    def swing_bound(self):
        return self.learned.swing_bound()

    def limit_tension(self, u_max):
        super().limit_tension(u_max)
        self.learned.limit_tension(u_max)
        self.fallback.limit_tension(u_max)

    # The tension felt by the fallback's observer: it predicts with the exact equations, as
    # the safety filter's certificates do, where the learned law's predicts with its model
    # (whose estimate drifts where the model is wrong).
    def felt(self, command):
        return self.fallback.felt(command)

    def command_for(self, felt):
        return self.fallback.command_for(felt)

    def felt_least(self, command, sigmas):
        return self.fallback.felt_least(command, sigmas)

    def residual(self):
        return self.learned.residual()

    def diagnostics(self):
        return {**self.learned.diagnostics(), 'flying': self.flying,
                'monitor': self.monitor or 'trusted', 'supervisor_switches': self.switches,
                'supervisor_takeback_steps': self.takeback,
                **{f'untrusted_{reason}': n for reason, n in self.reasons.items()}}
