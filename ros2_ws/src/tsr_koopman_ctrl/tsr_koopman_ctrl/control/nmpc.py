"""One nonlinear MPC, two models: real-time iteration (RTI) with multiple shooting.

`physics_nmpc` and `koopman_nmpc` are the same law; they differ only in the map x+ = f(x, u)
they plan with (`control/prediction_maps.py`): the planar equations (`PhysicsMap`, RK4 with
substeps) or the relifted learned model x+ = C (A psi_x(x) + B psi_u(x, u)) (`LearnedMap`).

Problem (every step, from the measured state x): tensions u_j piecewise constant on a grid of
N intervals (four lead ones of h, 2h, 3h, 4h, so the move that is optimised is the move that is
flown, then `interval` up to `horizon`: 39 intervals, 360 samples, 3.6 tau by default), node
states p_0 = x, p_1..p_N on the map,

    min  sum_j d_j (sum_i q_i m(y_{j+1,i}) + r (u_j - 3)^2) + y_N' P y_N
    s.t. |theta_j| <= theta_max - margin,  l_j - 1 <= overshoot_max,  l_j >= PLAN_MIN_LENGTH
         (soft, every node), 0 <= u_j <= u_max

with y = [theta, theta', ln l, l'] (a swing bound limits l' / l, so progress is exponential in
l), m(y) = sqrt(y^2 + eps^2) a smoothed 1-norm (near time-optimal: it keeps pulling on small
errors where a quadratic fades), P the continuous LQR cost-to-go at the target.

One RTI step (Diehl, Bock, Schloeder 2005), multiple shooting:

1. shift: every node of the previous plan advanced one sample on the map (one batched call;
   node j then sits at the new grid's time j), the tensions shifted by h, p_0 := x;
2. simulate: every interval from its node under its tension, all in one batch (`map.interval`,
   ~10 batched map calls on the default grid instead of 360 sequential ones; on the physics
   map one call of a compiled function), with the
   sensitivities A_j = d end_j / d p_j, b_j = d end_j / d u_j (on the learned map by default
   the one-step Jacobian at the interval's start, held; chained exactly on a step whose
   defects pass HELD_DEFECT_LIMIT); the defects end_j - p_{j+1} stay in the QP as affine
   terms, so no single-shooting rollout (whose open-loop-unstable length drifts off) is ever
   flown;
3. condense: the nodes are affine in the tension changes du, p = p_bar + G du
   (p_bar_{j+1} = end_j + A_j (p_bar_j - p_j), G_{j+1} = A_j G_j + b_j e_j'; on the physics
   map one banded triangular solve, `condense_banded`);
4. one dense QP in the N tension changes (DAQP, active set): the smoothed 1-norm replaced by
   its majorising quadratic at p_bar (m(y) <= m(y_bar) + (y^2 - y_bar^2) / (2 m(y_bar)), equal
   gradient, so a fixed point of the iteration is a stationary point of the problem), ln l
   linearised, |du| <= trust, the node bounds soft (DAQP's soft constraints, a quadratic
   penalty 1 / SOFT_RHO);
5. the plan moves by du, the nodes to p_bar + G du, and the first tension is flown.

Also in the QP: the tension bounds are the felt range the offset-free wrapper sets
(`felt_range`), and a total-variation term rate_weight * sum_j m_u(u_j - u_{j-1}) (u_{-1} the
tension flown last step, m_u the 1-norm smoothed by rate_smoothing, majorised the same way):
without it the default observer, which reads a 0.05-tau actuator lag as a fast gain change,
and this law's high gain near the target limit-cycle (docs/nmpc.md).

The first step, and a step whose QP fails or whose nodes leave the domain (a fallback,
counted), is a cold start: the linearised LQR law (Q = I, R = 1) flown on a guide map, refined
by up to COLD_ITERATIONS QP steps in single shooting with backtracking (`cold_start`). The
first step's trial plans roll out on `guide` (the learned map itself: 100-400 ms, paid while
the plant waits for the first command), a failed step's on `recovery` (on the learned law the
exact equations by default, ~10 ms: inside a running loop a cold start must fit a period or
two). A law without a plan that is offered one made for the same state by another law on the
same grid (`start_from`: the supervisor's fallback, when the learned law takes up again) starts
with one RTI step from its nodes instead; a law resumed after a pause in the run (`resume`)
with one RTI step from its own plan, unless the plant moved off it meanwhile. On trial
(`Law.on_trial`: the supervisor's fallback flies and this law is only judged) a failed step
or a failed start answers NaN, its plan dropped, with no cold start.
"""

import dataclasses
import functools
import math
from typing import ClassVar

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.law import Law, planar_state, WARM_UP_STATES
from tsr_koopman_ctrl.control.lqr import continuous_lqr_gain
from tsr_koopman_ctrl.control.prediction_maps import LearnedMap, PhysicsMap
from tsr_koopman_ctrl.control.settings import LawSettings, setting

#: Lead intervals in units of h (the first is h: the optimised move is the flown one).
LEAD_STEPS = (1, 2, 3, 4)
#: theta_max at or above this (a swing past pi is a tumble): no swing rows in the QP.
NO_SWING_BOUND = np.pi
#: The swing-bound margin for theta between nodes (the former physics NMPC's).
THETA_MARGIN = 0.003
#: The plans keep the predicted tether this long at least (half the paper's initial length):
#: the learned map is not trusted on a tether about to be reeled in completely.
PLAN_MIN_LENGTH = 0.005
#: QP steps of the cold start (single shooting, from the LQR plan), and halvings of a step
#: whose rollout leaves the domain before the step is refused.
COLD_ITERATIONS = 5
BACKTRACKS = 4
#: The largest defect (any component) of the nodes an RTI step starts from that the held
#: start sensitivities (`sensitivities: 'start'`) linearise: a larger one shows that they
#: predicted the last QP step badly (a large move of the plan on a short tether), and the
#: step chains them exactly instead. Held throughout, the defects of the nominal run from the
#: paper's start grow to 0.4 in theta' until the condensed plan reels the tether in past
#: nothing, 1 / l scales the QP's Hessian to 1e14 and DAQP cycles (a fallback); chained on
#: the three steps past the limit, no QP fails. Normal defects are ~0.002.
HELD_DEFECT_LIMIT = 0.1
#: A plan resumed after a pause (`Nmpc.resume`) is the next step's warm start while it
#: predicted the state measured then within this, any component (a model's one-step miss
#: within a run stays under ~0.07, its 99th percentile ~0.01); past it the plant moved off the
#: plan while the law was paused (the reel hold stopped the tether mid-deployment), and the
#: step is a cold start, as a run's first: from such a stale plan the learned law fell back in
#: 7 of 10 stops tried (docs/supervisor.md), from a cold start in none.
RESUME_MISS_LIMIT = 0.1
#: DAQP's soft-constraint weight (a violation s costs s^2 / (2 SOFT_RHO)) and the QP's
#: regularisation of du (a strictly convex QP whatever r).
SOFT_RHO = 1e-6
REGULARISATION = 1e-8
#: The default model of koopman_nmpc: koopman_default fine-tuned with retrieval data too
#: (models/README.md): a fast deployment brakes by reeling the tether back in.
MODEL = 'koopman_retrieval'


def prediction_grid(h, horizon, interval):
    """Interval lengths (tau): the lead ones, then `interval` up to about `horizon`."""
    lead = h * np.array(LEAD_STEPS, dtype=float)
    rest = max(int(round((horizon - lead.sum()) / interval)), 1)
    return np.r_[lead, np.full(rest, interval)]


def shift_plan(plan, starts, durations, age):
    """A plan's tensions (piecewise constant on the grid `starts`, `durations`) as seen `age`
    tau after it was made, on the same grid: each new interval's tension the old plan's mean
    over it (the last tension held past the horizon). The mean, not the value at the
    interval's middle: that would move every switch on the long intervals one step later
    each step, a lag the next QP step corrects only in part."""
    ends = starts + durations
    times = np.concatenate((starts, (ends[-1], ends[-1] + age + durations[-1])))
    integral = np.zeros(len(times))
    np.cumsum(np.append(plan, plan[-1]) * np.diff(times), out=integral[1:])
    lows, highs = starts + age, ends + age
    return (np.interp(highs, times, integral) - np.interp(lows, times, integral)) / durations


@dataclasses.dataclass(frozen=True)
class NmpcSettings(LawSettings):
    """The settings both backends share, declared once."""
    horizon: float = setting(3.6, 'prediction horizon [tau]', low=0.2, high=20.0)
    interval: float = setting(0.1, 'prediction interval after the four short lead ones [tau], '
                              'a multiple of the step h', low=0.01, high=1.0)
    # 0.8 by default: the swing bound every law is tuned and compared under (lab/tune.py).
    theta_max: float = setting(0.8, 'bound on |theta| at every prediction node, soft with a '
                               'stiff penalty [rad]; >= pi: no bound', low=0.01, high=3.2)
    # One cost for both backends, so that the physics NMPC measures what the learned model
    # costs: a frontier-ratio search's best for koopman_nmpc that also holds on a lagging
    # actuator (docs/tuning.md).
    q: tuple = setting((4.71, 4.798, 8.406, 7.511), "stage weights on the smoothed |.| of "
                       "[theta, theta', ln l, l']", low=0.0, tune=(1e-1, 1e2, 'log'))
    r: float = setting(0.07805, 'stage weight on (u - 3)^2', low=1e-9,
                       tune=(1e-3, 1e1, 'log'))
    overshoot_max: float = setting(0.005, 'bound on l - 1 at every prediction node (soft); '
                                   '>= 10: none', low=0.0, high=10.0)
    smoothing: float = setting(0.01, "the 1-norm's smoothing eps in sqrt(y^2 + eps^2)",
                               low=1e-6, high=1.0)
    rate_weight: float = setting(0.06, 'weight on the smoothed |u_j - u_{j-1}| along the plan, '
                                 'u_{-1} the tension flown last step (total variation: '
                                 'against chattering, not against a switch)', low=0.0, high=1e6)
    rate_smoothing: float = setting(0.03, "the tension changes' 1-norm smoothing", low=1e-6,
                                    high=10.0)
    move_weight: float = setting(0.0, 'weight on (u_0 - u_flown)^2, the first tension against '
                                 'the one flown last step', low=0.0, high=1e6)
    trust: float = setting(2.0, 'largest change of a planned tension per step (the QP trusts '
                           'the linearisation that far)', low=1e-3, high=10.0)
    qp_iterations: int = setting(1000, "DAQP's iteration limit per QP: a QP that needs more "
                                 'fails (a fallback) in a few ms instead of stalling the loop '
                                 "~40 ms at DAQP's own 10000 (a solved one takes tens)",
                                 low=10, high=100000)
    actuator_lag: float = setting(0.0, 'time constant of the tension actuator the plans model '
                                  '[tau]: the felt tension follows the planned one with this '
                                  'first-order lag (0: none)', low=0.0, high=10.0)


class Nmpc(Law):
    """The RTI machinery (module docstring); a subclass gives the map (`make_map`)."""

    Settings = NmpcSettings
    #: Exact interval sensitivities (False: the map may approximate them, `MapBase.interval`).
    exact_sensitivities = True
    #: QP steps of a cold start (`cold_start`).
    cold_iterations = COLD_ITERATIONS
    #: Condense in one LAPACK call (`condense_banded`), not interval by interval (`condense`).
    banded_condensing = False

    def __init__(self, settings=None, **kwargs):
        super().__init__(settings, **kwargs)
        s = self.settings
        self.map = self.make_map()
        #: The maps a cold start rolls its plans out on (`rollout`, `lqr_plan`): the first
        #: step's, and a failed step's.
        self.guide = self.make_guide()
        self.recovery = self.make_recovery()
        if abs(self.map.h - self.h) > 1e-12:
            raise ValueError(f'{self.name}: the map steps {self.map.h:g} tau, the loop '
                             f'h = {self.h:g}')
        if s.horizon <= self.h * sum(LEAD_STEPS):
            raise ValueError(f'{self.name}.horizon must exceed the lead intervals '
                             f'({self.h * sum(LEAD_STEPS):g} tau), got {s.horizon}')
        self.durations = prediction_grid(self.h, s.horizon, s.interval)
        self.counts = np.rint(self.durations / self.h).astype(int)
        if not np.allclose(self.counts * self.h, self.durations) or np.any(self.counts < 1):
            raise ValueError(f'{self.name}.interval must be a multiple of h = {self.h:g}, got '
                             f'{s.interval}')
        self.starts = np.r_[0.0, np.cumsum(self.durations)[:-1]]
        self.node_times = np.r_[self.starts, self.starts[-1] + self.durations[-1]]
        self.q = np.asarray(s.q, dtype=float)
        self.terminal = continuous_lqr_gain(self.q, s.r)[1]
        self.lqr_gain = continuous_lqr_gain(np.ones(4), 1.0)[0]
        self.theta_bound = (np.inf if s.theta_max >= NO_SWING_BOUND
                            else s.theta_max - THETA_MARGIN)
        self.lag = lag_model(self.durations, s.actuator_lag, self.h)
        self.reset()

    def make_map(self):
        raise NotImplementedError

    def make_guide(self):
        return self.map

    def make_recovery(self):
        return self.guide

    def reset(self):
        super().reset()
        #: The plan (N,) and its node states (N + 1, n), p_0 the state it was made from.
        self.plan = self.nodes = None
        #: DAQP's exit flag of the last QP; the tension flown last step (None: none yet).
        self.qp_status = 0
        self.flown = None
        #: The actuator's tension now by the lag model (None: none flown yet; the actuator
        #: starts on the first tension), and the felt tensions of the plan (N,).
        self.actuator = self.actuator_before = None
        self.felt_plan = None
        #: The state now less the map's one-step prediction of it (`residual`).
        self.missed = None
        #: Samples between the last state and the next (`elapsed`).
        self.age = 1
        #: A plan offered for the next step (`start_from`; None: none).
        self.offered = None
        #: The next step is the first after a pause (`resume`).
        self.resumed = False
        #: Another law flies and this one is judged (`on_trial`): a failed step is not
        #: recovered.
        self.trial = False
        #: RTI steps whose sensitivities were chained exactly (HELD_DEFECT_LIMIT).
        self.exact_steps = 0
        #: The tensions the plans may take: [0, u_max], or the felt range the offset-free
        #: wrapper sets ([phi(0), phi(u_max)]: what the actuator can make the plant feel).
        self.felt_range = (0.0, self.u_max)

    def warm_up(self):
        """`Law.warm_up`, and a failed step's cold start too: its map's functions (the
        nominal equations' on the learned law) are built now, not at a failure mid-run."""
        super().warm_up()
        for x in WARM_UP_STATES:
            self.cold_start(planar_state(x), guide=self.recovery)
        self.reset()
        self.map.compile()      # (the native build in the background: the same numbers)

    def limit_tension(self, u_max):
        super().limit_tension(u_max)
        self.felt_range = (0.0, self.u_max)    # a wrapper's bound_tension narrows it again

    def bound_tension(self, low, high):
        """The offset-free wrapper's felt range: the plans stay within what the actuator can
        make the plant feel."""
        self.felt_range = (float(low), float(high))

    # -- the RTI step -------------------------------------------------------------------------

    def compute(self, x):
        x = planar_state(x)
        offered, self.offered = self.offered, None
        resumed, self.resumed = self.resumed, False
        if self.plan is None:
            self.age = 1
            return self.start(x, offered)
        # 1. shift: node j advanced one sample lies at the new grid's time j (`age` samples
        # when the loop dropped states: the flown tension was held over them)
        age, self.age = self.age, 1
        shifted = np.clip(shift_plan(self.plan, self.starts, self.durations, age * self.h),
                          *self.felt_range)
        felt = np.append(self.felt_plan, self.felt_plan[-1])
        nodes = (self.map.step(self.nodes, felt) if age == 1 else
                 self.map.advance(self.nodes, felt, np.full(len(felt), age)))
        # nodes[0]: the last state advanced under what flew (after a pause, not what flew)
        self.missed = None if resumed else x - nodes[0]
        if resumed and not np.abs(x - nodes[0]).max() <= RESUME_MISS_LIMIT:
            self.flown = None       # (the hold flew last, a tension the law does not know)
            if self.trial:          # from the plan offered, as after a rest
                self.plan = self.nodes = self.felt_plan = None
                return self.start(x, offered)
            return self.fly(self.cold_start(x))
        nodes[0] = x
        step = self.iterate(nodes, shifted) if np.all(np.isfinite(nodes)) else None
        if step is None:
            # A failed QP or a node off the map's domain: a cold start from here (from the
            # shifted plan if its rollout stays in the domain, else from the LQR plan)
            self.fallbacks += 1       # (once, whether the cold start then solves or not)
            if self.trial:
                return self.unanswered(x)
            return self.fly(self.cold_start(x, shifted, count=False, guide=self.recovery))
        self.plan, self.nodes = step
        self.felt_plan = self.felt(self.plan)
        return self.fly(float(self.plan[0]))

    def start(self, x, offered):
        """The first tension without a plan of its own, flown: one RTI step from the plan
        `offered` (another law's for x, same grid; if that fails, a fallback: a recovery's cold
        start from it), else a cold start. On trial (`on_trial`) a failed start, or one with no
        plan offered, is a fallback answered NaN (`unanswered`)."""
        if offered is None and not self.trial:
            return self.fly(self.cold_start(x))
        if offered is not None and self.adopt(x, offered):
            return self.fly(float(self.plan[0]))
        self.fallbacks += 1
        if self.trial:
            return self.unanswered(x)
        return self.fly(self.cold_start(
            x, np.clip(np.array(offered[0], dtype=float), *self.felt_range), count=False,
            guide=self.recovery))

    def adopt(self, x, offered):
        """One RTI step from `offered` = (plan, nodes) made for x by another law: True if it
        solved (plan and nodes set), False otherwise."""
        plan, nodes = offered
        nodes = self.floored(np.array(nodes, dtype=float))
        nodes[0] = x
        step = self.iterate(nodes, np.clip(np.array(plan, dtype=float), *self.felt_range))
        if step is None:
            return False
        self.plan, self.nodes = step
        self.felt_plan = self.felt(self.plan)
        self.missed = None
        return True

    def on_trial(self, trial):
        self.trial = bool(trial)

    def unanswered(self, x):
        """A failed step on trial (`Law.on_trial`): no command and no plan (the next step
        starts again, from the plan offered then); a cold start would cost tens of ms."""
        self.observe(x)
        return math.nan

    def start_from(self, guess):
        if guess is not None and np.shape(guess[0]) == self.durations.shape and np.shape(
                guess[1]) == (len(self.durations) + 1, self.map.n):
            self.offered = guess      # (a plan on another grid is no start)

    def guess(self):
        return None if self.plan is None else (self.plan, self.nodes)

    def fly(self, tension):
        """Record `tension` as flown (the rate term's u_{-1}) and advance the lag model's
        actuator one sample under it."""
        self.flown = tension
        self.actuator_before = self.actuator
        if self.lag is not None:
            start = tension if self.actuator is None else self.actuator
            self.actuator = tension + (start - tension) * self.lag.decay
        return tension

    def elapsed(self, steps):
        """The next state comes `steps` samples after the last: the plan is shifted that far,
        the actuator model advanced under the tension flown, held over the ones between."""
        self.age = int(steps)
        if self.lag is not None and self.actuator is not None and steps > 1:
            self.actuator = self.flown + (self.actuator - self.flown) * self.lag.decay ** (
                steps - 1)

    def applied(self, tension):
        """`tension` flew this step, not the law's own (a clamp, an excitation, another law):
        it is the rate term's u_{-1} and the tension the lag model's actuator advanced under."""
        if tension == self.flown:
            return
        self.actuator = self.actuator_before
        self.fly(float(tension))
        if self.plan is not None and self.lag is None:
            # The plan's first interval is what flew: the next shift advances the state under it
            self.plan[0] = self.felt_plan[0] = self.flown

    def resume(self):
        """The plan stays the next step's warm start: that step shifts it one sample and, if
        the state measured then lies where the plan predicted it (RESUME_MISS_LIMIT: no sample
        missed, or a plant held at rest), makes one RTI step from it as every step does, so
        the first command after the pause continues the plan flown before it and costs what
        the others do; a plant that moved off the plan meanwhile (the reel hold stopped it
        mid-deployment) gets a cold start, as at a run's first state. Either way its miss is
        the pause's, not the model's: no `residual` that step."""
        self.offered, self.age, self.resumed = None, 1, True

    def observe(self, x):
        """Not flown this step: the plan is dropped (the next step starts again, `start`)."""
        self.plan = self.nodes = self.felt_plan = self.missed = self.offered = None
        self.actuator_before = self.actuator

    def prediction(self):
        return self.nodes

    def swing_bound(self):
        return math.inf if self.settings.theta_max >= NO_SWING_BOUND else self.settings.theta_max

    def prediction_times(self):
        return self.node_times

    def residual(self):
        return self.missed

    def felt(self, plan):
        """The tensions the plant feels on average over each interval of `plan` (N,): the plan
        itself, or with an actuator lag M plan + m a_0 (a_0 the actuator now; none flown yet:
        the plan's first tension, where the actuator starts)."""
        if self.lag is None:
            return np.asarray(plan, dtype=float)
        start = plan[0] if self.actuator is None else self.actuator
        return self.lag.matrix @ plan + self.lag.start * start

    def tension_gains(self, gains):
        """The condensed gains (N + 1, n, N) in the felt tensions, chained to the planned ones."""
        if self.lag is None:
            return gains
        matrix = self.lag.matrix
        if self.actuator is None:
            matrix = matrix.copy()
            matrix[:, 0] += self.lag.start
        return gains @ matrix

    def cold_start(self, x, plan=None, count=True, guide=None):
        """The first step, and the step after a failure: `plan` (default: the LQR law's, also
        where `plan`'s rollout leaves the domain) refined by up to COLD_ITERATIONS QP steps in
        single shooting: after each, the new plan is rolled out on the map from x, its step
        halved (up to BACKTRACKS times) until the rollout stays in the domain. The multiple-
        shooting steps that follow start from a plan whose nodes have no defects. If no QP
        step succeeds, the plan is flown as it is (a fallback, counted if `count`). The trial
        plans roll out on `guide` (default: the law's `guide`)."""
        guide = self.guide if guide is None else guide
        nodes = None if plan is None else self.rollout(x, plan, guide)
        if nodes is None or not in_domain(nodes):
            plan, nodes = self.lqr_plan(x, guide)
        solved = False
        for _ in range(self.cold_iterations):
            end, a, b = self.map.interval(nodes[:-1], self.felt(plan), self.counts,
                                          exact=self.exact_sensitivities)
            predicted, gains = self.condense(nodes, end, a, b)
            du = self.solve(predicted, self.tension_gains(gains), plan)
            if du is None:
                break
            for _ in range(BACKTRACKS):
                candidate = np.clip(plan + du, *self.felt_range)
                candidate_nodes = self.rollout(x, candidate, guide)
                if in_domain(candidate_nodes):
                    break
                du = 0.5 * du
            else:
                break
            plan, nodes, solved = candidate, candidate_nodes, True
        if guide is not self.map:
            # The steps that follow start from the plan flown on the law's own map (no
            # defects), where it stays in the domain.
            own = self.map.rollout(x, self.felt(plan), self.counts)
            nodes = own if in_domain(own) else nodes
        self.fallbacks += count and not solved
        self.plan, self.nodes, self.felt_plan = plan, nodes, self.felt(plan)
        return float(plan[0])

    def rollout(self, x, plan, guide=None):
        """The node states (N + 1, n) of `plan` flown from x, interval after interval, on the
        map the cold start is guided by (`guide`; single shooting: for the cold start only)."""
        return (guide or self.guide).rollout(x, self.felt(plan), self.counts)

    def lqr_plan(self, x, guide=None):
        """The linearised LQR law (Q = I, R = 1) flown on the map over the grid, its tension
        held over each interval: (plan (N,), node states (N + 1, n))."""
        guide = guide or self.guide
        plan, nodes = guide.feedback_rollout(x, dynamics.EQUILIBRIUM_TENSION, self.lqr_gain,
                                             self.felt_range, self.counts)
        if self.lag is not None:   # (the LQR law's tensions, flown through the lag)
            nodes = self.rollout(x, plan, guide)
        return plan, self.floored(nodes)

    def condense(self, nodes, end, a, b):
        """`condense_banded` or `condense` (`banded_condensing`)."""
        return (condense_banded if self.banded_condensing else condense)(nodes, end, a, b)

    def floored(self, nodes):
        """Node states with l >= PLAN_MIN_LENGTH and finite (a plan's linear prediction may reel
        the tether in past it; the map is not evaluated there)."""
        nodes = (np.array(nodes) if np.isfinite(nodes).all() else
                 np.nan_to_num(nodes, nan=0.0, posinf=10.0, neginf=-10.0))
        np.maximum(nodes[:, dynamics.LENGTH_OFFSET], PLAN_MIN_LENGTH - 1.0,
                   out=nodes[:, dynamics.LENGTH_OFFSET])
        return nodes

    def iterate(self, nodes, plan):
        """One RTI step from nodes (N + 1, n) (nodes[0] the measured state) and plan (N,):
        the new (plan, nodes), or None if the QP fails or an interval leaves the domain. Held
        sensitivities whose nodes' defects pass HELD_DEFECT_LIMIT are chained exactly."""
        with np.errstate(all='ignore'):
            end, a, b = self.map.interval(nodes[:-1], self.felt(plan), self.counts,
                                          exact=self.exact_sensitivities)
            if (not self.exact_sensitivities and in_domain(end)
                    and np.abs(end - nodes[1:]).max() > HELD_DEFECT_LIMIT):
                end, a, b = self.map.interval(nodes[:-1], self.felt(plan), self.counts)
                self.exact_steps += 1
        if not (in_domain(end) and np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return None
        predicted, gains = self.condense(nodes, end, a, b)
        gains = self.tension_gains(gains)
        du = self.solve(predicted, gains, plan)
        if du is None:
            return None
        new_plan = np.clip(plan + du, *self.felt_range)
        return new_plan, self.floored(predicted + gains @ (new_plan - plan))

    # -- the QP -------------------------------------------------------------------------------

    def qp_problem(self, predicted, gains, plan):
        """(hessian, linear, rows, lower, upper, soft) of the QP in du (module docstring):
        min 1/2 du' H du + linear' du s.t. lower[:N] <= du <= upper[:N] and
        lower[N:] <= rows du <= upper[N:], the rows marked `soft` soft."""
        s, n_nodes = self.settings, len(plan)
        states, g = predicted[1:], gains[1:]
        length = np.maximum(1.0 + states[:, dynamics.LENGTH_OFFSET], 1e-6)
        y = states.copy()
        y[:, dynamics.LENGTH_OFFSET] = np.log(length)
        y_gains = g.copy()
        y_gains[:, dynamics.LENGTH_OFFSET] /= length[:, None]
        # The majoriser's weights: d_j q_i / (2 m(y_bar)) on y^2.
        weight = self.durations[:, None] * self.q / (2.0 * np.sqrt(y * y + s.smoothing ** 2))
        root = np.sqrt(2.0 * weight)
        scaled = (root[:, :, None] * y_gains).reshape(-1, n_nodes)
        terminal_gain = y_gains[-1]
        hessian = scaled.T @ scaled + 2.0 * terminal_gain.T @ self.terminal @ terminal_gain
        hessian[np.diag_indices(n_nodes)] += 2.0 * s.r * self.durations + REGULARISATION
        linear = (scaled.T @ (root * y).ravel()
                  + 2.0 * s.r * self.durations * (plan - dynamics.EQUILIBRIUM_TENSION)
                  + 2.0 * terminal_gain.T @ (self.terminal @ y[-1]))
        if s.rate_weight > 0.0:
            # w sum_j m_u(u_j - u_{j-1}) (u_{-1} the tension flown last step), m_u the 1-norm
            # smoothed by rate_smoothing, majorised at the plan as the stage cost is: with D
            # the differences (u_j - u_{j-1}; the first none before a first flown tension),
            # H += 2 D' diag(rate) D (tridiagonal) and linear += 2 D' (rate * change)
            change = np.empty(n_nodes)
            np.subtract(plan[1:], plan[:-1], out=change[1:])
            change[0] = 0.0 if self.flown is None else plan[0] - self.flown
            rate = s.rate_weight / (2.0 * np.sqrt(change * change + s.rate_smoothing ** 2))
            diagonal = rate.copy()
            if self.flown is None:
                diagonal[0] = 0.0
            diagonal[:-1] += rate[1:]
            hessian[np.diag_indices(n_nodes)] += 2.0 * diagonal
            below = np.arange(1, n_nodes)
            hessian[below, below - 1] -= 2.0 * rate[1:]
            hessian[below - 1, below] -= 2.0 * rate[1:]
            weighted = rate * change
            weighted[:-1] -= weighted[1:]
            linear += 2.0 * weighted
        if s.move_weight > 0.0 and self.flown is not None:
            hessian[0, 0] += 2.0 * s.move_weight
            linear[0] += 2.0 * s.move_weight * (plan[0] - self.flown)
        low, high = self.felt_range
        lower = [np.maximum(low - plan, -s.trust)]
        upper = [np.minimum(high - plan, s.trust)]
        rows = []
        if np.isfinite(self.theta_bound):
            theta = states[:, dynamics.THETA]
            rows.append(g[:, dynamics.THETA])
            lower.append(-self.theta_bound - theta)
            upper.append(self.theta_bound - theta)
        offset = states[:, dynamics.LENGTH_OFFSET]
        rows.append(g[:, dynamics.LENGTH_OFFSET])
        lower.append(PLAN_MIN_LENGTH - 1.0 - offset)
        upper.append((s.overshoot_max if s.overshoot_max < 10.0 else np.inf) - offset)
        rows = np.vstack(rows)
        soft = np.zeros(n_nodes + len(rows), dtype=bool)
        soft[n_nodes:] = True
        return hessian, linear, rows, np.concatenate(lower), np.concatenate(upper), soft

    def solve(self, predicted, gains, plan):
        """The QP's du by DAQP, or None if it fails."""
        import daqp
        hessian, linear, rows, lower, upper, soft = self.qp_problem(predicted, gains, plan)
        sense = np.where(soft, 8, 0).astype(np.int32)
        du, _, status, _ = daqp.solve(hessian, linear, rows, upper, lower, sense,
                                      rho_soft=SOFT_RHO, iter_limit=self.settings.qp_iterations)
        self.qp_status = int(status)
        if status < 1 or not np.all(np.isfinite(du)):
            return None
        return np.asarray(du)


@dataclasses.dataclass(frozen=True)
class LagModel:
    """A first-order actuator lag on the grid: the felt tensions v = matrix u + start a_0
    (each the mean of the actuator over its interval, the tensions u held on theirs, a_0 the
    actuator at the start), and the actuator's decay over one sample h."""
    matrix: np.ndarray
    start: np.ndarray
    decay: float


def lag_model(durations, lag, h=dynamics.PAPER_STEP):
    """The `LagModel` of time constant `lag` on intervals `durations`; None for lag 0. Over an
    interval of length D from actuator a under u: a+ = u + (a - u) e, e = exp(-D / lag), and
    the mean is u + (a - u) w, w = lag / D (1 - e)."""
    if lag <= 0.0:
        return None
    n_intervals = len(durations)
    decay = np.exp(-durations / lag)
    mean = lag / durations * (1.0 - decay)
    actuator = np.zeros(n_intervals + 1)       # a_j = actuator[j] a_0 + gains[j] @ u
    actuator[0] = 1.0
    gains = np.zeros((n_intervals + 1, n_intervals))
    matrix, start = np.zeros((n_intervals, n_intervals)), np.zeros(n_intervals)
    for j in range(n_intervals):
        matrix[j] = mean[j] * gains[j]
        matrix[j, j] += 1.0 - mean[j]
        start[j] = mean[j] * actuator[j]
        gains[j + 1] = decay[j] * gains[j]
        gains[j + 1, j] += 1.0 - decay[j]
        actuator[j + 1] = decay[j] * actuator[j]
    return LagModel(matrix, start, float(np.exp(-h / lag)))


def in_domain(nodes):
    """True if node states (..., n) are finite and keep the tether longer than PLAN_MIN_LENGTH."""
    return bool(np.all(np.isfinite(nodes))
                and np.all(nodes[..., dynamics.LENGTH_OFFSET] > PLAN_MIN_LENGTH - 1.0))


def condense(nodes, end, a, b):
    """The nodes affine in the tension changes: (p_bar (N + 1, n), G (N + 1, n, N)) with
    p_bar_0 = nodes_0, G_0 = 0, p_bar_{j+1} = end_j + A_j (p_bar_j - nodes_j),
    G_{j+1} = A_j G_j + b_j e_j'."""
    n_nodes, n = a.shape[0], a.shape[1]
    predicted = np.empty((n_nodes + 1, n))
    gains = np.zeros((n_nodes + 1, n, n_nodes))
    predicted[0] = nodes[0]
    for j in range(n_nodes):
        predicted[j + 1] = end[j] + a[j] @ (predicted[j] - nodes[j])
        gains[j + 1, :, :j] = a[j] @ gains[j, :, :j]
        gains[j + 1, :, j] = b[j]
    return predicted, gains


def condense_banded(nodes, end, a, b):
    """`condense` in one call, ~3x faster on the default grid: the recursion is one
    block-bidiagonal unit lower-triangular system, L [p_bar | G] = [nodes_0 | 0;
    end_j - A_j nodes_j | b_j e_j'] (L: I on the diagonal, -A_j below it), solved by LAPACK's
    banded forward substitution. The same values to rounding, summed in another order."""
    from scipy.linalg.lapack import dtbtrs
    n_nodes, n = a.shape[0], a.shape[1]
    band_rows, band_columns, rhs_rows, rhs_columns = _condense_layout(n_nodes, n)
    band = np.zeros((2 * n, n * (n_nodes + 1)))
    band[band_rows, band_columns] = -a.ravel()
    rhs = np.zeros((n * (n_nodes + 1), n_nodes + 1))
    rhs[:n, 0] = nodes[0]
    rhs[n:, 0] = (end - np.einsum('jrc,jc->jr', a, nodes[:-1])).ravel()
    rhs[rhs_rows, rhs_columns] = b.ravel()
    solution, _ = dtbtrs(band, rhs, uplo='L', diag='U', overwrite_b=1)
    solution = solution.reshape(n_nodes + 1, n, n_nodes + 1)
    return solution[:, :, 0], solution[:, :, 1:]


@functools.cache
def _condense_layout(n_nodes, n):
    """Where `condense_banded` puts A_j (band storage of L: L[i, k] at [i - k, k]) and b_j (the
    right-hand side), in the order of a.ravel() and b.ravel()."""
    j, r, c = np.meshgrid(np.arange(n_nodes), np.arange(n), np.arange(n), indexing='ij')
    band_rows, band_columns = (n + r - c).ravel(), (n * j + c).ravel()
    j, r = np.meshgrid(np.arange(n_nodes), np.arange(n), indexing='ij')
    return band_rows, band_columns, (n * (j + 1) + r).ravel(), (j + 1).ravel()


@dataclasses.dataclass(frozen=True)
class PhysicsNmpcSettings(NmpcSettings):
    law: ClassVar[str] = 'physics_nmpc'


class PhysicsNmpc(Nmpc):
    """The NMPC on the planar equations (`PhysicsMap`): the law a GNC engineer would fly."""

    name = 'physics_nmpc'
    Settings = PhysicsNmpcSettings
    # Its map is float64 and smooth: the banded condensing's rounding (~1e-13 on its runs)
    # stays rounding. The learned map evaluates in float32, where a last-bit change of a node
    # flips roundings that the loop amplifies (1e-6 in 200 steps): it condenses as it did.
    banded_condensing = True

    def make_map(self):
        return PhysicsMap(self.h)


@dataclasses.dataclass(frozen=True)
class KoopmanNmpcSettings(NmpcSettings):
    law: ClassVar[str] = 'koopman_nmpc'
    model: str = setting(MODEL, 'model directory, or the name of a shipped model')
    sensitivities: str = setting('start', "each interval's sensitivities: 'exact' (the "
                                 "one-step Jacobians at every sample, chained) or 'start' "
                                 "(the one at the interval's start, held: one batched "
                                 'Jacobian a step instead of ~10)', choices=('exact', 'start'))
    precision: str = setting('float32', "the map's floating-point type: 'float32' about "
                             'halves its time (~1e-7 relative rounding)',
                             choices=('float64', 'float32'))
    cold_iterations: int = setting(COLD_ITERATIONS, "QP steps of a cold start (the first "
                                   "step, a failed QP) before its first tension is flown: "
                                   "each costs a rollout of the learned map (~20 ms); the steps "
                                   "that follow refine the plan anyway", low=1, high=20)
    cold_guide: str = setting('model', "what the first step's cold start (a run's first "
                              "state) rolls its trial plans out on: 'model' (the learned map, "
                              "sample by sample: 25-450 ms, paid while the plant waits for the "
                              "first command) or 'physics' (the nominal equations, one "
                              "compiled-graph call: ~10 ms, and another law: the plans it starts "
                              "from differ); the QP steps use the learned map either way",
                              choices=('model', 'physics'))
    recovery_guide: str = setting('physics', "what a failed step's cold start (a failed QP, "
                                  "a node off the domain) rolls its trial plans out on, as "
                                  "cold_guide: 'physics' (~10 ms) keeps a real-time loop within "
                                  "a period or two where 'model' stalls it for tens",
                                  choices=('model', 'physics'))


class KoopmanNmpc(Nmpc):
    """The NMPC on the relifted learned model (`LearnedMap`)."""

    name = 'koopman_nmpc'
    Settings = KoopmanNmpcSettings
    filtered = True

    def make_map(self):
        from tsr_koopman_ctrl.control.koopman_lqr import load_model
        #: The learned model (the offset-free observer predicts with it too).
        self.model = load_model(self.settings.model)
        self.exact_sensitivities = self.settings.sensitivities == 'exact'
        self.cold_iterations = self.settings.cold_iterations
        return LearnedMap(self.model, dtype=self.settings.precision)

    def make_guide(self):
        #: The nominal equations' map, one for both guides that take it.
        self.physics_map = PhysicsMap(self.h)
        return self.physics_map if self.settings.cold_guide == 'physics' else self.map

    def make_recovery(self):
        return self.physics_map if self.settings.recovery_guide == 'physics' else self.map
