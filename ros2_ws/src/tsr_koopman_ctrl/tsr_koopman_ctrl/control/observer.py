"""Disturbance observer: an extended Kalman filter on the planar state plus one input disturbance.

Why a filter and not a residual: the prototype estimated the actuator gain from the l' residual
of a one-step prediction, but differencing l' over h = 0.01 multiplies 1e-3 sensor noise by
~140. Here the disturbance is one more state of a Kalman filter, so it is read mostly from l
and l' together over the filter's memory, and the filter also returns a filtered state for the
control law.

Augmented model (one sample h, command u held, s = [x (4), d])::

    x+ = F(x, phi(u, d)) + w_x       F: the one-step predictor (physics or learned Koopman)
    d+ = d + w_d                     random walk: d is constant or slow
    y  = x + v                       every planar component measured, v ~ N(0, sensor_std^2)

    phi(u, d) = d u   ('gain': actuator gain, mass error; d starts at 1)
    phi(u, d) = u + d ('additive': tension bias, or gravity/orbit terms in the l'' equation)

The disturbance enters exactly where the tension does, so the offset-free target is the
nominal one (x = 0, applied u = 3) and the command that produces an applied u is phi^-1
(Pannocchia & Rawlings 2003; Maeder, Borrelli & Morari 2009: input disturbance model, which is
observable here since (A, B) at the target is controllable with C = I). The EKF's Jacobians
come from forward differences of F on one batched call, so any predictor works.

Optional `actuator_lag_tau` = T > 0 adds the actuator's tension a as a state (s = [x, a, d]):
a+ = u + (a - u) exp(-h / T), and F is driven by phi of a's mean over the sample. Without it
an actuator lag is read as a fast-moving d, which with the gain model and lags >= 0.1 tau sets up
a limit cycle between d and the lag (docs/robustness.md).
"""

import math

import numpy as np
from tsr_sim import dynamics

PLANAR = dynamics.PLANAR_DIM
#: The estimate's tether length is kept above this: the equations divide by l.
MIN_LENGTH = 1e-3
#: The first measurement after a pause continues the filter while its normalised innovation
#: squared stays below this (the chi-square 0.999 quantile for the 4 components measured).
RESUME_GATE = 18.47


def physics_predictor(h=dynamics.PAPER_STEP, substeps=10):
    """F from the nominal equations (tsr_sim.dynamics), RK4 with the simulator's substeps, one
    state at a time on Python floats (`dynamics.step`: ~4x faster than numpy on a batch of 6)."""
    def predict(x, u):
        return np.array([dynamics.step(state, command, h, substeps)
                         for state, command in zip(np.atleast_2d(x), np.broadcast_to(
                             u, (np.atleast_2d(x).shape[0],)))])
    return predict


def koopman_predictor(model):
    """F from the learned lifted model: x+ = C (A psi_x(x) + B psi_u(x, u))."""
    def predict(x, u):
        batch = np.atleast_2d(x)
        return model.step(batch, np.broadcast_to(u, (len(batch),))).reshape(np.shape(x))
    return predict


class DisturbanceObserver:
    """EKF estimating the planar state and an input disturbance d from noisy full-state y.

    Tuning (per sample h): `sensor_std` the measurement noise; `rate_noise_std` the model error
    on theta' and l' (the unmodelled actuator lag and predictor error land here);
    `disturbance_walk_std` how fast d may move (its estimate's bandwidth);
    `initial_disturbance_std` how far from nominal d may start.
    """

    def __init__(self, predictor=None, disturbance='gain', sensor_std=1e-3,
                 rate_noise_std=1e-4, position_noise_std=1e-6, disturbance_walk_std=3e-3,
                 initial_disturbance_std=0.2, disturbance_limits=None, actuator_lag_tau=0.0,
                 actuator_noise_std=1e-3, h=dynamics.PAPER_STEP, eps=1e-6):
        if disturbance not in ('gain', 'additive'):
            raise ValueError(f"disturbance must be 'gain' or 'additive', got {disturbance!r}")
        self.predictor = predictor or physics_predictor()
        self.kind = disturbance
        self.nominal = 1.0 if disturbance == 'gain' else 0.0
        if disturbance_limits is None:
            disturbance_limits = (0.3, 3.0) if disturbance == 'gain' else (-3.0, 3.0)
        self.limits = disturbance_limits
        self.eps, self.h, self.lag = eps, float(h), float(actuator_lag_tau)
        self.sensor_variance = float(sensor_std) ** 2
        actuator = [actuator_noise_std] if self.lag > 0.0 else []
        q = np.array([position_noise_std, rate_noise_std, position_noise_std, rate_noise_std,
                      *actuator, disturbance_walk_std]) ** 2
        self.process_covariance = np.diag(q)
        self.initial_covariance = np.diag(np.r_[np.full(PLANAR, float(sensor_std) ** 2),
                                                np.square(actuator),
                                                float(initial_disturbance_std) ** 2])
        self.size = q.size
        self.reset()

    def reset(self):
        self.estimate = None       # [x_hat (4), (a_hat), d_hat]
        self.covariance = None
        #: y - the one-step prediction of the planar state (None until a prediction was made)
        self.innovation = None
        self.actuator_pending = False   # a_hat is set from the first command it sees
        #: The next update is the first after a pause (`resume`).
        self.resumed = False

    def resume(self):
        """After a pause (the controller inactive; the plant may have flown its reel hold, a
        tension the filter does not know, over samples it does not see): the next update
        corrects the state if its measurement lies where the filter predicts it (no sample
        missed, or a plant at rest), judged by its innovation against the predicted
        covariance (RESUME_GATE), else starts the state again from it. Either way the
        disturbance estimate stands that update (the innovation may be the hold's, no sign of
        the actuator's), its variance too: restarted at its initial variance, the estimate
        would be learnt again and the command move with it."""
        self.resumed = self.estimate is not None

    @property
    def state(self):
        return self.estimate[:PLANAR]

    @property
    def disturbance(self):
        return self.nominal if self.estimate is None else float(self.estimate[-1])

    @property
    def spread(self):
        """The standard deviation of the disturbance estimate (its prior's before the first
        update)."""
        variance = (self.initial_covariance if self.covariance is None
                    else self.covariance)[-1, -1]
        return math.sqrt(max(float(variance), 0.0))

    def applied(self, command, disturbance=None):
        """The tension the plant feels for `command`, by the disturbance model."""
        d = self.disturbance if disturbance is None else disturbance
        return d * command if self.kind == 'gain' else command + d

    def command_for(self, applied):
        """The command that makes the plant feel `applied` (phi^-1)."""
        d = self.disturbance
        return applied / d if self.kind == 'gain' else applied - d

    def update(self, y, previous_command):
        """Fold in the measurement y taken after `previous_command` was held for one sample
        (None at the first sample); return the filtered planar state."""
        y = np.asarray(y, dtype=float)[:PLANAR]
        resumed, self.resumed = self.resumed, False
        if self.estimate is not None and previous_command is not None:
            predicted, jacobian = self.linearised_step(self.estimate, float(previous_command))
            if (np.all(np.isfinite(predicted)) and np.all(np.isfinite(jacobian))
                    and not (resumed and self.surprised(y, predicted, jacobian))):
                self.innovation = y - predicted[:PLANAR]
                return self.correct(y, predicted, jacobian, disturbance=not resumed)
        # first sample, after a pause the filter did not predict (`resume`), or the estimate
        # left the model's domain (a noisy l near 0): restart from the measurement, keeping the
        # disturbance learnt so far; the actuator starts on the first command, as the
        # simulated plant's does
        self.actuator_pending = self.lag > 0.0
        self.innovation = None
        start = np.r_[y, [np.nan] * (self.size - PLANAR - 1), self.disturbance]
        start[dynamics.LENGTH_OFFSET] = max(start[dynamics.LENGTH_OFFSET], MIN_LENGTH - 1.0)
        covariance = self.initial_covariance.copy()
        if resumed:
            covariance[-1, -1] = self.covariance[-1, -1]
        self.estimate, self.covariance = start, covariance
        return self.state.copy()

    def surprised(self, y, predicted, jacobian):
        """True if y lies outside the filter's prediction: its normalised innovation squared
        against the predicted covariance past RESUME_GATE."""
        covariance = (jacobian[:PLANAR] @ self.covariance @ jacobian[:PLANAR].T
                      + self.process_covariance[:PLANAR, :PLANAR]
                      + self.sensor_variance * np.eye(PLANAR))
        innovation = y - predicted[:PLANAR]
        return not innovation @ np.linalg.solve(covariance, innovation) <= RESUME_GATE

    def coast(self, command, samples):
        """Predict `samples` samples ahead under `command` held, with no measurement (a
        real-time loop dropped them): the estimate and its growing covariance."""
        for _ in range(samples):
            if self.estimate is None:
                return
            predicted, jacobian = self.linearised_step(self.estimate, float(command))
            if not (np.all(np.isfinite(predicted)) and np.all(np.isfinite(jacobian))):
                return                   # the next update restarts from the measurement
            self.covariance = jacobian @ self.covariance @ jacobian.T + self.process_covariance
            self.estimate = predicted

    def correct(self, y, predicted, jacobian, disturbance=True):
        """The Kalman measurement update after the prediction `predicted`, Jacobian F_s; the
        disturbance estimate left as predicted unless `disturbance` (a gain of 0 for it: the
        Joseph form keeps the covariance right for any gain)."""
        covariance = jacobian @ self.covariance @ jacobian.T + self.process_covariance
        size = self.size
        innovation_cov = covariance[:PLANAR, :PLANAR] + self.sensor_variance * np.eye(PLANAR)
        gain = np.linalg.solve(innovation_cov, covariance[:PLANAR]).T   # P H' S^-1
        if not disturbance:
            gain[-1] = 0.0
        estimate = predicted + gain @ (y - predicted[:PLANAR])
        correction = np.eye(size)
        correction[:, :PLANAR] -= gain
        covariance = (correction @ covariance @ correction.T
                      + self.sensor_variance * gain @ gain.T)   # Joseph form
        estimate[-1] = np.clip(estimate[-1], *self.limits)
        estimate[dynamics.LENGTH_OFFSET] = max(estimate[dynamics.LENGTH_OFFSET],
                                               MIN_LENGTH - 1.0)
        self.estimate, self.covariance = estimate, 0.5 * (covariance + covariance.T)
        return self.state.copy()

    def linearised_step(self, estimate, command):
        """The predicted augmented state and its Jacobian, by forward differences of F."""
        x, d = estimate[:PLANAR], estimate[-1]
        jacobian = np.eye(self.size)
        if self.lag > 0.0:
            if self.actuator_pending:   # (sets it in self.estimate, which `estimate` is)
                estimate[PLANAR], self.actuator_pending = command, False
            decay = np.exp(-self.h / self.lag)
            mean_weight = self.lag / self.h * (1.0 - decay)   # mean of a over the sample
            actuator = estimate[PLANAR]
            driving = command + (actuator - command) * mean_weight
            jacobian[PLANAR, PLANAR] = decay
        else:
            driving = command
        u = self.applied(driving, d)
        du_dd = driving if self.kind == 'gain' else 1.0
        steps = self.eps * np.maximum(1.0, np.abs(x))
        batch = np.vstack([x, x + np.diag(steps), x])
        inputs = np.r_[np.full(PLANAR + 1, u), u + self.eps]
        out = self.predictor(batch, inputs)
        jacobian[:PLANAR, :PLANAR] = ((out[1:PLANAR + 1] - out[0]) / steps).T
        response = (out[-1] - out[0]) / self.eps
        jacobian[:PLANAR, -1] = response * du_dd
        if self.lag > 0.0:
            du_da = (d if self.kind == 'gain' else 1.0) * mean_weight
            jacobian[:PLANAR, PLANAR] = response * du_da
            return np.r_[out[0], command + (actuator - command) * decay, d], jacobian
        return np.r_[out[0], d], jacobian
