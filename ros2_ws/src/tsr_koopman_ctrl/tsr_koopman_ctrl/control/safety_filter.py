"""Predictive safety filter: a law's command flies only while the robot can still be saved
from where it leads (Wabersich & Zeilinger; Black-Box Simplex, Mehmood et al. 2021).

Each step the filtered law (the learned law under its supervisor) asks for a tension u. From
the state x+ that u leads to on the exact planar equations (the tension the plant feels by the
offset-free observer's disturbance estimate, `Law.felt`), a backup must exist that keeps every
bound of the loop (`Bounds`: the swing bound, the tension range, the tether above its floor and
inside the simulator's domain) and ends in a set the reel hold keeps invariant (`terminal`).
The backups tried, cheapest first:

1. the reel hold from x+ (`tsr_sim.dynamics.hold_tension`: a speed loop stops the tether, then
   the length is held while the robot librates);
2. the verified law's plan (`physics_nmpc`, the NMPC on the exact equations) made from x+, then
   the reel hold; skipped once the step has used its `deadline`. (The rest of the learned
   law's own plan, flown open loop on the exact equations, is no backup: the length is
   unstable open loop and over 3.6 tau such a tail ran the tether out to l = 10-35.)

A certified u flies, and the backup that certified it is kept (the certificate). Otherwise the
verified law's tension from the state now flies if its plan is certified (it deploys where the
kept backup may only brake), else the previous certificate's next tension: it was certified
from the state the plant is now in on the exact equations, so on the model a backup exists at
every step once one existed (recursive feasibility). The plant is not the model: the kept
certificate is checked again from the measured state, and one that no longer holds (`lapsed`)
gives way to the verified law flown closed loop, as it is before any certificate exists
(`uncertified`: a start from which no backup is certified).

Under the supervisor a refused command hands the plant to its verified fallback, which plans
in the shadow at every step (`shadow: auto`) so that it takes over warm, from its own plan, as
the verified law alone flies (taking over cold, or from a plan not its own, its plans drifted
off the verified law's and lost robots it held); while it flies, the filter passes it, or with
`fallback_commands: certified` certifies its commands as the learned law's. A
command's certificate plans with the least tension the actuator surely gives
(`actuator_sigmas` of the observer's uncertainty below its estimate): an actuator not yet seen
pulling is known only to the observer's prior.

Terminal set: with the tether stopped (l' = 0) the planar equations keep E = theta'^2 / 2 +
3/2 sin^2 theta constant, so the swing stays within asin(sqrt(2 E / 3)); the reel hold needs
the tension l ((1 + theta')^2 + 3 cos^2 theta - 1), at most l (3 + 2 E + 2 sqrt(2 E)) on that
orbit. A state whose tether has stopped (|l'| <= speed_tolerance; its length and theta' taken
where the hold stops it, the angular momentum l^2 (1 + theta') kept), whose E keeps the swing
within the bound and whose hold tension stays within the felt range is held there for ever.

What it guarantees: on the nominal planar model (circular orbit, the tension felt as the
observer estimates it), once a certificate exists no command flown leads to a state from which
the backup breaks a bound, to the certificate's RK4 accuracy (`substeps`) and its margins
(TIGHTENING). What it does not: an actuator lag, sensor noise or an orbit unlike the model move
the plant off the certificate by more than no margin bounds in advance; each new certificate is
made from the measured state, so such errors are met a step later, and what they cost is
measured by Monte Carlo campaigns (docs/supervisor.md), not proven.
"""

import dataclasses
import hashlib
import math
import pathlib
import time
from typing import ClassVar

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.law import planar_state, Wrapper
from tsr_koopman_ctrl.control.settings import build, LawSettings, setting
from tsr_koopman_ctrl.control.supervisor import FALLBACK

#: How a step was flown (ControllerStatus.certificate, /diagnostics): the filtered law's
#: tension, certified; the previous certificate's next tension; the verified law's, certified
#: from here; the verified law's with no certificate yet.
CERTIFIED, KEPT, REPLANNED, UNCERTIFIED = 'certified', 'kept', 'replanned', 'uncertified'
#: The kept certificate no longer held from the state the plant reached (a plant unlike the
#: model): the verified law flew, uncertified.
LAPSED = 'lapsed'
#: The supervisor's verified fallback flew (the filter passes it), or took over this step when
#: the filter refused the learned law's tension (`Law.hand_over`).
VERIFIED, HANDED = 'verified', 'handed_over'
#: What the rollouts' native builds are generated from besides the plant (their cache key).
_SOURCE_DIGEST = hashlib.sha256(pathlib.Path(__file__).read_bytes()).hexdigest()[:16]
#: A certificate keeps the bounds with this fraction of the swing tolerance and the terminal
#: speed, and 5% of the hold's tension range spare (`SafetyFilter.check`).
TIGHTENING = 0.5


@dataclasses.dataclass(frozen=True)
class SafetyFilterSettings(LawSettings):
    law: ClassVar[str] = 'safety_filter'
    backup: str = setting('auto', "the verified law whose plans certify a command "
                          "('physics_nmpc': the NMPC on the exact equations, with the law's "
                          "cost and bounds; 'hold': the reel hold alone; 'auto': "
                          "physics_nmpc for a law filtered by default, the learned NMPC, "
                          "none for the others); 'none': unfiltered",
                          choices=('auto', 'none', 'hold', 'physics_nmpc'))
    swing_tolerance: float = setting(0.004, 'how far past the swing bound a backup may swing '
                                     "[rad]: the verified law's plans are soft-bounded",
                                     low=0.0, high=1.0)
    length_floor: float = setting(0.005, 'shortest tether a backup may reach (l, '
                                  'dimensionless)', low=1e-6, high=0.5)
    hold_steps: int = setting(200, 'samples of reel hold a backup ends with (it stops the '
                              'tether within them)', low=1, high=100000)
    speed_tolerance: float = setting(0.002, "|l'| at which the reel hold has stopped the "
                                     'tether (the terminal set)', low=1e-9, high=1.0)
    substeps: int = setting(2, 'RK4 substeps per sample of a backup rollout', low=1,
                            high=100)
    deadline: float = setting(0.0, "wall seconds a step may have used before the verified "
                              "law's plan is tried (a certificate not ready in time counts as "
                              "missing: the kept one flies); 0: none, every step certified "
                              "in full (a run then depends on nothing but its inputs)",
                              low=0.0, high=10.0)
    fallback_commands: str = setting('passed', "the supervisor's verified fallback's "
                                     "commands: 'passed' unchecked (it flies as it flies "
                                     "alone); 'certified' as the learned law's, a refused one "
                                     "replaced by the filter's (the verified law's certified "
                                     "command or the kept certificate's next tension)",
                                     choices=('passed', 'certified'))
    actuator_sigmas: float = setting(1.0, "standard deviations of the observer's actuator "
                                     'estimate by which the tension a certificate may plan '
                                     'with is lowered (an actuator not yet seen pulling is '
                                     "known only to the observer's prior: a weak one taken "
                                     'at its nominal gain lost the robot)', low=0.0,
                                     high=10.0)


@dataclasses.dataclass(frozen=True)
class Bounds:
    """What a backup must keep: |theta| <= swing, l >= floor, l <= PLAUSIBLE_LENGTH."""

    swing: float
    floor: float
    tolerance: float


class Rollouts:
    """Backups rolled out on the exact planar equations, compiled once (CasADi): from x0, each
    sample flies either its given felt tension or the reel hold's, clamped to the felt range.
    One function of one input column [x0; felt range; (tension, hold) per sample], evaluated
    as the NMPC's physics map is (`BatchFunction`: native code once built, bit for bit)."""

    def __init__(self, h, substeps, samples, gain=dynamics.HOLD_GAIN):
        import casadi

        from tsr_koopman_ctrl.control.prediction_maps import BatchFunction
        x = casadi.SX.sym('x', dynamics.PLANAR_DIM)
        given = casadi.SX.sym('given', 2)          # (felt tension, 1 for the reel hold)
        felt_range = casadi.SX.sym('range', 2)
        theta, rate, offset, speed = (x[i] for i in range(dynamics.PLANAR_DIM))
        free = dynamics.planar_rates(theta, rate, offset, speed, 0.0, sin=casadi.sin,
                                     cos=casadi.cos)[dynamics.LENGTH_RATE]
        hold = free + gain * speed
        u = given[1] * hold + (1.0 - given[1]) * given[0]
        u = casadi.fmin(casadi.fmax(u, felt_range[0]), felt_range[1])
        end, _ = dynamics.symbolic_rk4(x, u, h, substeps)
        sample = casadi.Function('sample', [x, given, felt_range], [end])
        roll = sample.mapaccum('roll', samples)
        column = casadi.MX.sym('column', dynamics.PLANAR_DIM + 2 + 2 * samples)
        n = dynamics.PLANAR_DIM
        states = roll(column[:n], casadi.reshape(column[n + 2:], 2, samples),
                      column[n:n + 2])
        description = ('rollouts', h, substeps, samples, gain, _SOURCE_DIGEST)
        name = 'tsr_rollouts_' + hashlib.sha256(repr(description).encode()).hexdigest()[:12]
        self.function = BatchFunction(casadi.Function(name, [column], [casadi.vec(states)]),
                                      description)
        self.samples = samples

    def __call__(self, x0, tensions, felt_range):
        """States (samples + 1, 4) of the backup that flies `tensions` (a felt tension per
        sample; NaN: the reel hold's) from x0."""
        n = min(len(tensions), self.samples)
        tensions = np.asarray(tensions[:n], dtype=float)
        hold = ~np.isfinite(tensions)
        column = self.function.arguments[0]
        column[:4] = x0
        column[4:6] = felt_range
        given, flags = column[6::2], column[7::2]     # (tension, hold) per sample
        given[:] = 0.0
        flags[:] = 1.0                                # past the tensions given: the hold
        given[:n] = np.where(hold, 0.0, tensions)
        flags[:n] = hold
        states = self.function.run()[0].reshape(self.samples, dynamics.PLANAR_DIM)
        return np.vstack([np.asarray(x0, dtype=float), states])

    def compile(self):
        """Start its native build (`BatchFunction.compile`)."""
        self.function.compile()


def terminal(x, bounds, felt_high, speed_tolerance, gain=dynamics.HOLD_GAIN):
    """True if the reel hold keeps x within `bounds` for ever (module docstring)."""
    theta, rate, offset, speed = x
    if not abs(speed) <= speed_tolerance:
        return False
    length = offset + 1.0
    stopped = length + speed / gain        # where the speed loop stops the tether
    if not stopped >= bounds.floor:
        return False
    w = (1.0 + rate) * (length / stopped) ** 2
    energy = 0.5 * (w - 1.0) ** 2 + 1.5 * math.sin(theta) ** 2
    if energy > 1.5 * math.sin(min(bounds.swing, dynamics.TUMBLING_SWING)) ** 2:
        return False
    return stopped * (3.0 + 2.0 * energy + 2.0 * math.sqrt(2.0 * energy)) <= felt_high


class SafetyFilter(Wrapper):
    """`law` (a law as deployed: offset-free, supervised) flown under the filter (module
    docstring); `verified` builds the bare verified law whose plans certify (None: the reel
    hold alone). Two are built: one plans from the state a command leads to, one from the
    state now (when the law's command is not certified), each warm from its own last plan
    while it plans on consecutive steps. A law itself: its name, settings and model are the
    filtered law's."""

    def __init__(self, law, verified=None, settings=None, **overrides):
        super().__init__(law)
        self.verified, self.probe = ((None, None) if verified is None else
                                     (verified(), verified()))
        self.filter_settings = s = build(SafetyFilterSettings, settings, overrides)
        swing = law.swing_bound()
        self.bounds = Bounds(dynamics.TUMBLING_SWING if swing >= dynamics.TUMBLING_SWING
                             else swing, s.length_floor, s.swing_tolerance)
        plan = (0 if self.verified is None else
                int(round(self.verified.settings.horizon / self.h)) + 10)
        self.hold = Rollouts(self.h, s.substeps, s.hold_steps)
        self.planned = Rollouts(self.h, s.substeps, max(plan, 400) + s.hold_steps)
        self.reset()

    # -- what the wrapper forwards --------------------------------------------------------

    @property
    def flying(self):
        return self.law.flying

    @property
    def monitor(self):
        return self.law.monitor

    @property
    def switches(self):
        return self.law.switches

    def reset(self):
        self.law.reset()
        for verified in self.verified_laws():
            verified.reset()
        self.backup_plan = None       # felt tensions per sample from the next state (NaN: hold)
        self.planned_at = {}          # the step each verified law last planned at
        self.flew_verified = False    # the last rescue flew the verified law's plan from x
        self.corrections = 0
        self.correction_sum = 0.0
        self.steps = 0
        self.certificate = ''
        self.backup_used = ''
        self.counts = {name: 0 for name in (CERTIFIED, KEPT, REPLANNED, LAPSED, UNCERTIFIED,
                                            VERIFIED, HANDED)}
        self.late = 0
        self.requested = math.nan

    def verified_laws(self):
        return () if self.verified is None else (self.verified, self.probe)

    def resume(self):
        """The filtered law and the verified laws resume (`Law.resume`), the verified laws
        warm from their plans as on consecutive steps; the kept certificate stays (it flies
        only once checked again from the state measured, as every step)."""
        self.law.resume()
        for verified in self.verified_laws():
            verified.resume()

    def warm_up(self):
        self.law.warm_up()
        for verified in self.verified_laws():
            verified.warm_up()
        for x in (dynamics.PAPER_INITIAL_STATE, dynamics.equilibrium_state()):
            self.check(x, [0.0], (0.0, self.u_max))
        self.reset()
        for rollouts in (self.hold, self.planned):
            rollouts.compile()   # (the native build in the background: the same numbers)

    def bound_tension(self, low, high):
        self.law.bound_tension(low, high)

    def elapsed(self, steps):
        """States dropped: the kept backup and the verified laws' plans move on as far."""
        self.law.elapsed(steps)
        for verified in self.verified_laws():
            verified.elapsed(steps)
        if self.backup_plan is not None:
            self.backup_plan = self.backup_plan[steps - 1:]

    def observe(self, x):
        self.law.observe(x)

    def applied(self, command):
        self.law.applied(command)

    def limit_tension(self, u_max):
        super().limit_tension(u_max)
        for verified in self.verified_laws():
            verified.limit_tension(u_max)

    # -- the filter ---------------------------------------------------------------------------

    def compute(self, x):
        start = time.perf_counter()
        x = planar_state(x)
        self.steps += 1
        asked = self.law.compute(x)
        self.requested = asked
        fallback = self.law.flying == FALLBACK
        if fallback and (self.filter_settings.fallback_commands == 'passed'
                         or not math.isfinite(asked)):
            # The supervisor's verified fallback flies, warm from its own plans as the
            # verified law alone flies (`shadow`), by default unchecked: certified, its refused
            # commands gave way to the filter's plans and settled later. Unchecked, from where
            # the learned law led on a weak lagging actuator, it ran the tether out of the
            # domain (`fallback_commands`, docs/supervisor.md).
            self.certificate, self.backup_plan = VERIFIED, None
            self.counts[VERIFIED] += 1
            return asked
        felt_range = (self.felt(0.0), self.felt(self.u_max))
        backup = None
        if math.isfinite(asked):
            asked = min(max(asked, 0.0), self.u_max)
            backup = self.certify(x, self.felt(asked), self.surely_felt(), start)
        if backup is not None:
            self.certificate = VERIFIED if fallback else CERTIFIED
            self.backup_used, self.backup_plan = backup
            self.counts[self.certificate] += 1
            return asked
        handed = self.law.hand_over('certificate')      # (None while the fallback flies)
        if handed is not None and math.isfinite(handed):
            self.certificate, self.backup_plan = HANDED, None
            self.counts[HANDED] += 1
            command = min(max(handed, 0.0), self.u_max)
        else:
            command = self.rescue(x, felt_range, start)
            if self.flew_verified and not fallback:
                # The fallback flies from the next step: it starts from the plan that flew
                # this one, not cold (one sample behind, which its first RTI step absorbs).
                self.law.start_from(self.verified.guess())
        self.corrections += 1
        if math.isfinite(asked):
            self.correction_sum += abs(command - asked)
        return command

    def surely_felt(self):
        """The felt tensions a certificate of the law's command may plan with: from the least
        the plant feels for no tension to the least it surely feels for the limit
        (`actuator_sigmas`). (The verified law's own plans, when the command is refused, keep
        the nominal range: they fly what it would fly alone.)"""
        sigmas = self.filter_settings.actuator_sigmas
        low = self.felt(0.0)
        return low, max(self.law.felt_least(self.u_max, sigmas), low)

    def certify(self, x, felt, felt_range, start):
        """(backup, its felt tensions from the state `felt` leads to) if a backup from there
        keeps the bounds, else None; tried cheapest first (module docstring)."""
        after = dynamics.step(x, felt, self.h, self.filter_settings.substeps)
        if not dynamics.in_domain(after):
            return None
        hold = np.full(self.filter_settings.hold_steps, np.nan)
        if self.check(after, hold, felt_range, self.hold):
            return 'hold', hold
        if self.verified is None:
            return None
        if self.late_at(start):
            self.late += 1
            return None
        plan = self.verified_plan(self.probe, after, felt, felt_range)
        if plan is not None and self.check(after, plan, felt_range):
            return 'verified', plan
        return None

    def rescue(self, x, felt_range, start):
        """The tension flown when the law's is not certified: the verified law's from x if its
        plan is certified (it deploys where the kept backup may only brake); else the kept
        certificate's next one if the certificate still holds from x (it was made from the
        state the plant was predicted to reach); else the verified law's own, closed loop:
        a kept backup is open loop, and flown on a plant unlike the model (a lag) for a few
        hundred steps it tumbled the robot where the verified law held it."""
        kept = self.backup_plan
        if kept is not None and not len(kept):
            kept = np.full(1, np.nan)                # past its end a backup is the hold
        plan = None
        if self.verified is not None and (kept is None or not self.late_at(start)):
            plan = self.verified_plan(self.verified, x, None, felt_range)
        self.flew_verified = plan is not None
        if plan is not None and self.check(x, plan, felt_range):
            self.certificate, self.backup_plan, felt = REPLANNED, plan[1:], plan[0]
        elif kept is not None and self.check(x, kept, felt_range, kept=True):
            self.certificate, self.backup_plan, felt = KEPT, kept[1:], kept[0]
            self.flew_verified = False
        else:
            self.certificate = UNCERTIFIED if kept is None else LAPSED
            self.backup_plan = None
            felt = np.nan if plan is None else plan[0]
        self.counts[self.certificate] += 1
        if not math.isfinite(felt):
            felt = float(dynamics.hold_tension(x, u_max=felt_range[1]))
            felt = min(max(felt, felt_range[0]), felt_range[1])
        command = self.command_for(felt)
        return min(max(command, 0.0), self.u_max)

    def check(self, x, tensions, felt_range, rollouts=None, kept=False):
        """True if flying `tensions` (felt, per sample; NaN: the reel hold), then the reel
        hold, from x keeps the bounds and ends in the terminal set. A new certificate keeps
        them with a margin (TIGHTENING of the swing tolerance, the terminal speed and the
        hold's tension range) that a `kept` one, checked again from the state the plant did
        reach, may use: the plant integrates more finely than the certificate."""
        rollouts = rollouts or self.planned
        states = rollouts(x, tensions, felt_range)
        if not np.all(np.isfinite(states)):
            return False
        b, s = self.bounds, self.filter_settings
        tight = 1.0 if kept else TIGHTENING
        length = states[:, dynamics.LENGTH_OFFSET] + 1.0
        if (np.abs(states[:, dynamics.THETA]).max() > b.swing + tight * b.tolerance
                or length.min() < b.floor or length.max() > dynamics.PLAUSIBLE_LENGTH):
            return False
        return terminal(states[-1], b, felt_range[1] * (1.0 - (1.0 - tight) * 0.1),
                        s.speed_tolerance * tight)

    def late_at(self, start):
        """True if the step begun at `start` (perf_counter) has used its deadline."""
        deadline = self.filter_settings.deadline
        return deadline > 0.0 and time.perf_counter() - start > deadline

    def verified_plan(self, law, x, felt, felt_range):
        """`law`'s plan from x (a verified law), a felt tension per sample (its first flown at
        x), warm from its own last plan when it planned the step before, else a cold start
        (from the filtered law's plan, a short-tether start under a swing bound converged to
        reeling the tether in and lost the robot). `felt`: the tension flown just before x
        (None: its own)."""
        if self.planned_at.get(id(law)) != self.steps - 1:
            law.observe(x)
        if felt is not None:
            law.applied(felt)
        law.bound_tension(*felt_range)
        law.compute(x)
        self.planned_at[id(law)] = self.steps
        guess = law.guess()
        if guess is None:
            return None
        counts = np.rint(np.diff(law.prediction_times()) / self.h).astype(int)
        return np.repeat(np.asarray(guess[0], dtype=float), counts)

    def diagnostics(self):
        return {**self.law.diagnostics(), 'certificate': self.certificate or 'none',
                'certificate_backup': self.backup_used or 'none',
                'safety_corrections': self.corrections,
                'safety_correction_sum': self.correction_sum,
                'certificates_late': self.late,
                **{f'steps_{name}': count for name, count in self.counts.items()}}
