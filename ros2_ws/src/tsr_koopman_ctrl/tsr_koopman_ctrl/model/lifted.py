"""A trained deep Koopman model evaluated in numpy: the controller's form of the model.

The lifted linear system (paper eq. (9)-(11)) with our fixes::

    z = psi_x(x) = [x; Phi((x - mean) / std)]            (K + n)
    z+ = A z + B u_hat,   u_hat = psi_u(x, u) = psi_ux(x) psi_uu(u),   x = C z,  C = [I 0]

psi_uu is strictly increasing, so u = psi_uu^-1(u_hat / psi_ux(x)) inverts psi_u exactly (the
paper's printed inverse does not). A model trained with `momentum_power` p > 0 evolves
s = coordinates.to_model(x, p) (a scaled momentum in place of theta') in place of x: then
psi_x(x) = [s; Phi((s - mean) / std)], C z = s, and every method that returns states maps them
back (`coordinates.to_state`); p = 0 is the paper's form. `LiftedModel` mirrors
`learning.deep_koopman.DeepKoopman` in float64; tests check the two agree. Torch is not needed
here: the controller's hot path is plain numpy.
"""

import math

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.model import coordinates, model_file


def softplus(v):
    return np.logaddexp(0.0, v)


class MonotoneMap:
    """psi_uu(u) = a s + b + sum_j c_j tanh(d_j s + e_j), s = (u - mid) / half, a, c, d > 0."""

    #: The floating-point type of the array evaluations (`LiftedModel.astype`).
    dtype = np.float64

    def __init__(self, tensors, tension_range):
        low, high = tension_range
        self.mid, self.half = 0.5 * (low + high), 0.5 * (high - low)
        self.slope = float(softplus(tensors['input_map.slope'])) + 1e-3
        self.offset = float(tensors['input_map.offset'])
        self.amplitude = softplus(tensors['input_map.amplitude'])
        self.steepness = softplus(tensors['input_map.steepness'])
        self.shift = tensors['input_map.shift']
        #: (amplitude, steepness, shift) of each tanh term as Python floats, for the scalar
        #: evaluations (`value_at`, `slope_at`).
        self.terms = list(zip(self.amplitude.tolist(), self.steepness.tolist(),
                              self.shift.tolist()))

    def __call__(self, u):
        s = (np.asarray(u, dtype=self.dtype)[..., None] - self.mid) / self.half
        bumps = self.amplitude * np.tanh(self.steepness * s + self.shift)
        return self.slope * s[..., 0] + self.offset + bumps.sum(axis=-1)

    def derivative(self, u):
        """d psi_uu / du on an array (`slope_at` for a scalar)."""
        s = (np.asarray(u, dtype=self.dtype)[..., None] - self.mid) / self.half
        sech2 = 1.0 - np.tanh(self.steepness * s + self.shift) ** 2
        return (self.slope + (self.amplitude * self.steepness * sech2).sum(axis=-1)) / self.half

    def value_at(self, u):
        """psi_uu at a scalar u, on Python floats (equal to `__call__` to rounding): the inverse
        evaluates it a few times per control step, where numpy's per-call cost would dominate."""
        s = (float(u) - self.mid) / self.half
        return self.slope * s + self.offset + sum(a * math.tanh(d * s + e)
                                                  for a, d, e in self.terms)

    def slope_at(self, u):
        """d psi_uu / du at a scalar u (>= a / half > 0)."""
        s = (float(u) - self.mid) / self.half
        total = self.slope
        for a, d, e in self.terms:
            decay = math.exp(-2.0 * abs(d * s + e))
            total += a * d * 4.0 * decay / (1.0 + decay) ** 2   # sech^2 without overflow
        return total / self.half

    def inverse(self, value, low=0.0, high=None, tol=1e-12, guess=None):
        """The u with psi_uu(u) = value. It exists for every value: psi_uu is strictly
        increasing with slope >= a > 0, so onto. The bracket starts at [low, high] (default: the
        tension range) and widens until it holds the root; then Newton steps from `guess` (a
        controller's last tension) or the bracket's middle, falling back to bisection whenever a
        step would leave the bracket (so it always converges)."""
        lo, hi = float(low), float(self.mid + self.half if high is None else high)
        width = hi - lo
        while self.value_at(lo) > value:
            lo, width = lo - width, 2.0 * width
        while self.value_at(hi) < value:
            hi, width = hi + width, 2.0 * width
        u = guess if guess is not None and lo < guess < hi else 0.5 * (lo + hi)
        for _ in range(200):
            error = self.value_at(u) - value
            if abs(error) <= tol or hi - lo <= tol:
                break
            if error < 0.0:
                lo = u
            else:
                hi = u
            step = u - error / self.slope_at(u)
            u = step if lo < step < hi else 0.5 * (lo + hi)
        return u


class Mlp:
    def __init__(self, tensors, prefix, activation):
        self.layers = []
        i = 0
        while f'{prefix}.{i}.weight' in tensors:
            self.layers.append((tensors[f'{prefix}.{i}.weight'].T.copy(),
                                tensors[f'{prefix}.{i}.bias']))
            i += 2
        self.activation = np.tanh if activation == 'tanh' else elu

    def __call__(self, v):
        for weight, bias in self.layers[:-1]:
            v = self.activation(v @ weight + bias)
        weight, bias = self.layers[-1]
        return v @ weight + bias

    def with_tangents(self, v, tangents):
        """The output at v (N, inputs) and its directional derivatives along `tangents` (N, k,
        inputs), (N, k, outputs): forward-mode differentiation, layer by layer."""
        def times(tangents, weight):
            # One 2-D product: numpy multiplies a stack of matrices one by one (3x slower at
            # 39 x 4 tangents of width 128).
            return (tangents.reshape(-1, weight.shape[0]) @ weight).reshape(
                tangents.shape[:-1] + weight.shape[1:])

        for weight, bias in self.layers[:-1]:
            v = self.activation(v @ weight + bias)
            # tanh' = 1 - tanh^2; elu' = 1 on the positive side, exp = elu + 1 on the other.
            slope = 1.0 - v ** 2 if self.activation is np.tanh else np.minimum(v, 0.0) + 1.0
            tangents = slope[:, None, :] * times(tangents, weight)
        weight, bias = self.layers[-1]
        return v @ weight + bias, times(tangents, weight)


def elu(v):
    return np.where(v > 0.0, v, np.expm1(np.minimum(v, 0.0)))


class LiftedModel:
    """psi_x, psi_u and its inverse, and the lifted (A, B, C), from a model directory."""

    #: The floating-point type psi_x, psi_u, step and step_jacobians compute in (`astype`).
    dtype = np.float64

    def __init__(self, tensors, config, metadata=None):
        self.path = None              # the directory it was loaded from, if any
        self.config = config
        self.metadata = metadata or {}
        self.n = config.state_dim
        self.power = config.momentum_power
        self.mean, self.std = tensors['state_mean'], tensors['state_std']
        self.lift = Mlp(tensors, 'lift', config.activation)
        self.input_gain = Mlp(tensors, 'input_gain', config.activation)
        self.input_map = MonotoneMap(tensors, config.tension_range)
        if config.anchor_equilibrium:
            self.anchor_at(dynamics.equilibrium_state(self.n), config.anchor_tension)
        self.A, self.B = tensors['A'], tensors['B']
        self.C = np.eye(self.n, config.lifted_dim)

    @property
    def envelope(self):
        """(low (n,), high (n,)): the box of the states the model was trained on (the model
        file's `envelope`), or None for a file without one."""
        box = self.metadata.get('envelope')
        if not box:
            return None
        return np.asarray(box['low'], dtype=float), np.asarray(box['high'], dtype=float)

    def anchor_at(self, x, u):
        """Shift the last biases so Phi(x) = 0 and psi_uu(u) = 0: the torch model's
        `anchor_equilibrium`, folded into the constants once instead of subtracted per call."""
        weight, bias = self.lift.layers[-1]
        s = coordinates.to_model(np.asarray(x, dtype=float), self.power)
        self.lift.layers[-1] = (weight, bias - self.lift((s - self.mean) / self.std))
        self.input_map.offset -= float(self.input_map(u))

    @classmethod
    def load(cls, path):
        """A model directory, or the name of a shipped model (`shipped.resolve`)."""
        from tsr_koopman_ctrl.model.shipped import resolve
        directory = resolve(path)
        model = cls(*model_file.load(directory))
        model.path = str(directory)
        return model

    def reference(self):
        """(z_d, u_hat_d) = (psi_x(0), psi_u(0, u_d)): the deployed equilibrium, lifted; u_d the
        model's anchor tension (3 unless it was retrained on a plant that needs another)."""
        origin = dynamics.equilibrium_state(self.n)
        return self.psi_x(origin), float(self.psi_u(origin, self.config.anchor_tension))

    def state_weight(self, spec):
        """Q' on the lifted state: 'lifted' (I), 'state' (C^T C), C^T diag(q) C for q of n, or
        C^T Q C for a positive semidefinite n x n Q."""
        c = self.C
        if isinstance(spec, str):
            weights = {'lifted': np.eye(c.shape[1]), 'state': c.T @ c}
            if spec not in weights:
                raise ValueError(f"state weight must be 'lifted', 'state' or {self.n} weights, "
                                 f'got {spec!r}')
            return weights[spec]
        q = np.asarray(spec, dtype=float)
        if q.shape == (self.n,):
            q = np.diag(q)      # one check below: a diagonal is semidefinite iff q >= 0
        if q.shape != (self.n, self.n) or not (
                np.allclose(q, q.T) and np.linalg.eigvalsh(q).min() >= -1e-9):
            raise ValueError(f'state weights must be {self.n} numbers >= 0 or a symmetric '
                             f'positive semidefinite {self.n} x {self.n} matrix, got '
                             f'{np.asarray(spec).tolist()}')
        return c.T @ q @ c

    def astype(self, dtype):
        """A copy that evaluates psi_x, psi_u, step and step_jacobians in `dtype` (e.g.
        float32: about twice as fast on a CPU, ~1e-7 relative rounding); the other methods
        are for float64 models only."""
        import copy
        cast = copy.copy(self)
        cast.dtype = np.dtype(dtype).type
        for name in ('mean', 'std', 'A', 'B'):
            setattr(cast, name, getattr(self, name).astype(dtype))
        for name in ('lift', 'input_gain'):
            network = copy.copy(getattr(self, name))
            network.layers = [(w.astype(dtype), b.astype(dtype)) for w, b in network.layers]
            setattr(cast, name, network)
        cast.input_map = copy.copy(self.input_map)
        cast.input_map.dtype = cast.dtype
        for name in ('amplitude', 'steepness', 'shift'):
            setattr(cast.input_map, name, getattr(self.input_map, name).astype(dtype))
        return cast

    def psi_x(self, x):
        return self.lift_model_state(self.model_state(x))

    def psi_ux(self, x):
        return self.input_gain_at(self.model_state(x))

    def psi_u(self, x, u):
        return self.psi_ux(x) * self.input_map(u)

    def model_state(self, x):
        """s, the state the model evolves, of physical states x (x itself when p = 0)."""
        return coordinates.to_model(np.asarray(x, dtype=self.dtype), self.power)

    def lift_model_state(self, s):
        return np.concatenate([s, self.lift((s - self.mean) / self.std)], axis=-1)

    def input_gain_at(self, s):
        """psi_ux at model states s."""
        raw = self.input_gain((s - self.mean) / self.std)[..., 0]
        return self.config.min_input_gain + softplus(raw)

    def tension_from_input(self, x, u_hat, input_gain=None, guess=None):
        """Invert psi_u at state x: the tension u with psi_u(x, u) = u_hat (not clamped).
        `input_gain`: psi_ux(x) if the caller has it already; `guess`: a nearby tension."""
        gain = float(self.psi_ux(x)) if input_gain is None else input_gain
        return self.input_map.inverse(u_hat / gain, guess=guess)

    def predict(self, x0, u, relift=False):
        """Roll the lifted system from states x0 (N, n) under tensions u (N, T): the states read
        through C, (N, T + 1, n). The input gain uses the predicted state, as in training.

        `relift`: lift the predicted state again before every step, z_k = psi_x(x_k), so the
        model serves as a one-step map x+ = C (A psi_x(x) + B psi_u(x, u)) instead of a linear
        system in z. Slower (one lift per step); along the physics NMPC's bang-bang deployment
        from the paper's start far more accurate beyond 30 steps (docs/comparison.md). One
        start may be given as x0 (n,), u (T,)."""
        x0, u = prediction_inputs(x0, u, self.n)
        if relift:
            states = [x0]
            for k in range(u.shape[1]):
                states.append(self.step(states[-1], u[:, k]))
            return np.stack(states, axis=1)
        z = self.psi_x(x0)
        states = [z[:, :self.n]]
        for k in range(u.shape[1]):
            gain = self.input_gain_at(z[:, :self.n])
            z = z @ self.A.T + (gain * self.input_map(u[:, k]))[:, None] * self.B.T
            states.append(z[:, :self.n])
        return coordinates.to_state(np.stack(states, axis=1), self.power)

    def step(self, x, u):
        """The relifted one-step map on a batch, x (N, n), u (N,) -> x+ (N, n):
        x+ = C (A psi_x(x) + B psi_u(x, u)) (in the model's state, mapped back)."""
        following = (self.psi_x(x) @ self.A[:self.n].T
                     + self.psi_u(x, u)[:, None] * self.B[:self.n].T)
        return coordinates.to_state(following, self.power)

    def step_jacobians(self, x, u):
        """The one-step map on a batch and its derivatives, analytic (forward mode through the
        networks): (x+ (N, n), d x+ / d x (N, n, n), d x+ / d u (N, n))."""
        physical = np.atleast_2d(np.asarray(x, dtype=self.dtype))
        u = np.asarray(u, dtype=self.dtype)
        n = self.n
        x = self.model_state(physical)      # from here on x is the model's state s
        # d ((s - mean) / std) / dx, one direction per state component.
        if self.power:
            into = coordinates.to_model_jacobian(physical, self.power).astype(self.dtype)
            directions = into.transpose(0, 2, 1) / self.std
        else:
            directions = np.broadcast_to(np.diag(1.0 / self.std), (len(x), n, n))
        normalised = (x - self.mean) / self.std
        lifted, d_lifted = self.lift.with_tangents(normalised, directions)
        raw, d_raw = self.input_gain.with_tangents(normalised, directions)
        raw, d_raw = raw[:, 0], d_raw[:, :, 0]
        gain = self.config.min_input_gain + softplus(raw)
        d_gain = d_raw / (1.0 + np.exp(-raw))[:, None]      # softplus' = sigmoid
        mapped = self.input_map(u)
        a_x, b_x = self.A[:self.n], self.B[:self.n, 0]
        a_state, a_lift = a_x[:, :n], a_x[:, n:]
        following = (x @ a_state.T + lifted @ a_lift.T
                     + (gain * mapped)[:, None] * b_x[None, :])
        # d x+ / d x_k = A_state e_k + A_lift dPhi/dx_k + b (psi_uu(u) d psi_ux / dx_k).
        d_state = ((d_lifted @ a_lift.T).transpose(0, 2, 1)
                   + b_x[None, :, None] * (mapped[:, None] * d_gain)[:, None, :])
        d_tension = (gain * self.input_map.derivative(u))[:, None] * b_x[None, :]
        if not self.power:
            return following, a_state[None] + d_state, d_tension
        # Through the coordinates: d s / d x into the model, d x / d s back out.
        back = coordinates.to_state_jacobian(following, self.power).astype(self.dtype)
        d_state = back @ (a_state[None] @ into + d_state)
        return (coordinates.to_state(following, self.power), d_state,
                (back @ d_tension[:, :, None])[:, :, 0])

    def lift_jacobian(self, x=None):
        """dpsi_x/dx at x (default: the equilibrium), (lifted_dim, n): exact, the lifting
        network differentiated in forward mode (`Mlp.with_tangents`)."""
        x = dynamics.equilibrium_state(self.n) if x is None else np.asarray(x, dtype=float)
        into = coordinates.to_model_jacobian(x, self.power)[0]     # d s / d x
        s = coordinates.to_model(x, self.power)
        directions = (into.T / self.std)[None]     # d((s - mean) / std) / dx, per component
        _, d_lifted = self.lift.with_tangents(((s - self.mean) / self.std)[None], directions)
        return np.vstack([into, d_lifted[0].T])

    def local_linear_model(self, x=None):
        """(J, B_x): the state part of the lifted model's one-step map linearised at x (default:
        the equilibrium) in the lifted input, x+ ~ J x + B_x u_hat; J = A_x dpsi_x/dx (and
        d x / d s of the step's end ahead of both when the model evolves s)."""
        x = dynamics.equilibrium_state(self.n) if x is None else np.asarray(x, dtype=float)
        jacobian, b_x = self.A[:self.n] @ self.lift_jacobian(x), self.B[:self.n]
        if not self.power:
            return jacobian, b_x
        s = self.model_state(x)
        following = (self.lift_model_state(s) @ self.A[:self.n].T
                     + self.input_gain_at(s) * self.input_map(self.config.anchor_tension)
                     * self.B[:self.n, 0])
        back = coordinates.to_state_jacobian(following, self.power)[0]
        return back @ jacobian, back @ b_x

    def controllability_rank(self):
        return controllability_rank(self.A, self.B)


def prediction_inputs(x0, u, n):
    """(x0 (N, n), u (N, T)) as float arrays, one start also as x0 (n,), u (T,); the one-line
    ValueError every model's predict gives for other shapes."""
    x0, u = np.atleast_2d(np.asarray(x0, dtype=float)), np.asarray(u, dtype=float)
    if u.ndim == 1 and len(x0) == 1:
        u = u[None]
    if x0.ndim != 2 or x0.shape[1] != n or u.ndim != 2 or len(u) != len(x0):
        raise ValueError(f'predict takes x0 (N, {n}) and u (N, T), got x0 {np.shape(x0)} and '
                         f'u {np.shape(u)}')
    return x0, u


def controllability_matrix(a, b, normalise=True):
    """[B, AB, ..., A^(N-1) B] with (optionally) each column scaled to unit norm."""
    columns = [b[:, 0]]
    for _ in range(a.shape[0] - 1):
        columns.append(a @ columns[-1])
        if normalise:
            columns[-1] = columns[-1] / max(np.linalg.norm(columns[-1]), 1e-300)
    if normalise:
        columns[0] = columns[0] / max(np.linalg.norm(columns[0]), 1e-300)
    return np.stack(columns, axis=1)


def controllability_rank(a, b):
    """Numerical rank (numpy's default tolerance) of the column-normalised controllability
    matrix; normalising the columns does not change the rank but keeps A^k B representable."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)   # float64 tolerance
    return int(np.linalg.matrix_rank(controllability_matrix(a, b)))
