"""Dimensionless deployment dynamics of a tethered space robot (TSR), ROS-free and vectorised.

Model: Jin, Zhang, Huang, "Data-driven optimal control of TSR deployment with learning based
Koopman operator" (arXiv 2307.07713), eq. (1)-(3), after Williams (2008). Time is tau = Omega t,
length l = length / L, tension u = T / (m Omega^2 L); ``tsr_sim.units`` converts to and from SI.

State layout (the one definition every module uses)::

    planar (n = 4):  x = [theta, theta', l - 1, l']
    3-D    (n = 6):  x = [theta, theta', l - 1, l', beta, beta']

The 3-D layout extends the planar one, so ``x[..., :4]`` is always the in-plane state. Every
function here takes arrays of shape (..., n) with tension u of shape (...) and dispatches on n.

The paper prints ``beta tan(beta)`` in the theta equation of the 3-D model; the dimensionally
consistent term (Williams 2008) is ``beta' tan(beta)``, which is what is implemented.
"""

import math

import numpy as np

THETA, THETA_RATE, LENGTH_OFFSET, LENGTH_RATE, BETA, BETA_RATE = range(6)
PLANAR_DIM = 4
SPATIAL_DIM = 6
STATE_NAMES = ('theta', 'theta_rate', 'length_offset', 'length_rate', 'beta', 'beta_rate')

#: The deployed equilibrium x = 0 is held by the tension u = 3 (paper, Section II-A).
EQUILIBRIUM_TENSION = 3.0
#: The largest tension the system commands or accepts, dimensionless: the top of the paper's
#: sampled range (Table 1). Every limit in the project (the simulator's command check, the
#: controller's clamp, the MPC's bound, the frontier) derives from this one number.
TENSION_LIMIT = 5.0
#: |theta| past which the robot is tumbling, not librating: beyond the local horizontal the
#: gravity gradient (-3 sin(theta) cos(theta)) turns the tether away from the deployed
#: equilibrium, towards the opposite vertical. The simulator halts a run there.
TUMBLING_SWING = 0.5 * math.pi
#: The paper's sample period in tau (Section IV): one RK4 step of the learned model.
PAPER_STEP = 0.01
#: The paper's initial deployment state (Section IV-D): l = 0.01, l' = 0.5.
PAPER_INITIAL_STATE = np.array([0.0, 0.0, -0.99, 0.5])
#: Table 1 of the paper: ranges of the sampled initial states and of the random tension.
TABLE1_STATE_LOW = np.array([-2.5, -1.0, -0.99, 0.0])
TABLE1_STATE_HIGH = np.array([0.5, 1.0, 0.0, 2.0])
TABLE1_TENSION_RANGE = (0.0, TENSION_LIMIT)


def equilibrium_state(dim=PLANAR_DIM):
    """Return the deployed equilibrium (tether fully out, aligned with the local vertical)."""
    check_state_dim(dim)
    return np.zeros(dim)


def planar_rates(theta, rate, offset, speed, u, sin=math.sin, cos=math.cos,
                 frame_rate=1.0, gravity=1.0, frame_acceleration=0.0):
    """The planar equations, written once: d/dtau of [theta, theta', l - 1, l'] under tension
    u, for floats, numpy arrays or CasADi symbols alike (give their `sin` and `cos`).

    The orbit's terms default to the circular orbit's: the local frame turning at the rate 1
    (`frame_rate`, nu'), not accelerating (`frame_acceleration`, nu''), under the gravity
    gradient 1 (`gravity`, mu / (r^3 n^2)); an eccentric orbit gives its own
    (`tsr_sim.variants`). The defaults leave the circular equations' arithmetic exactly as it
    is (a multiplication by 1.0, a subtraction of 0.0)."""
    length, w = offset + 1.0, rate + frame_rate
    sin_t, cos_t = sin(theta), cos(theta)
    return (rate,
            -2.0 * (speed / length) * w - gravity * 3.0 * sin_t * cos_t - frame_acceleration,
            speed, length * (w * w + gravity * 3.0 * cos_t * cos_t - gravity) - u)


def rk4(rates, state, u, dt, substeps, path=None):
    """RK4, written once: `state` a tuple of components (floats, arrays or CasADi symbols),
    `rates(*state, u)` their derivatives, u held over dt in `substeps` steps. Appends every
    substep's state to `path` when given."""
    step = dt / substeps
    half, sixth = 0.5 * step, step / 6.0
    for _ in range(substeps):
        k1 = rates(*state, u)
        k2 = rates(*(x + half * k for x, k in zip(state, k1)), u)
        k3 = rates(*(x + half * k for x, k in zip(state, k2)), u)
        k4 = rates(*(x + step * k for x, k in zip(state, k3)), u)
        state = tuple(x + sixth * (a + 2.0 * b + 2.0 * c + d)
                      for x, a, b, c, d in zip(state, k1, k2, k3, k4))
        if path is not None:
            path.append(state)
    return state


def _numpy_planar_rates(theta, rate, offset, speed, u):
    return planar_rates(theta, rate, offset, speed, u, np.sin, np.cos)


def derivative(x, u):
    """Return dx/dtau for states x (..., 4 or 6) under tension u (...)."""
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    check_state_dim(x.shape[-1])
    if x.shape[-1] == PLANAR_DIM:
        return np.stack(_numpy_planar_rates(*np.moveaxis(x, -1, 0), u), axis=-1)
    theta, w, v = x[..., THETA], x[..., THETA_RATE] + 1.0, x[..., LENGTH_RATE]
    length = x[..., LENGTH_OFFSET] + 1.0
    sin_t, cos_t = np.sin(theta), np.cos(theta)
    stretch = v / length
    beta, beta_rate = x[..., BETA], x[..., BETA_RATE]
    sin_b, cos_b = np.sin(beta), np.cos(beta)
    theta_acc = 2.0 * w * (beta_rate * sin_b / cos_b - stretch) - 3.0 * sin_t * cos_t
    beta_acc = -2.0 * stretch * beta_rate - (w * w + 3.0 * cos_t * cos_t) * sin_b * cos_b
    length_acc = length * (beta_rate ** 2 + (w * w + 3.0 * cos_t * cos_t) * cos_b * cos_b
                           - 1.0) - u
    return np.stack([x[..., THETA_RATE], theta_acc, v, length_acc, beta_rate, beta_acc], axis=-1)


def rk4_step(x, u, h=PAPER_STEP, substeps=1):
    """Advance x (..., 4 or 6) by one sample period h with u held constant, using `substeps`
    RK4 steps (`rk4`).

    The paper samples with one RK4 step of h = 0.01. Near l -> 0 with large l' that single step
    is inaccurate (docs/physics.md, numerics); the simulator uses substeps for the plant.
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    if x.shape[-1] == PLANAR_DIM:
        return np.stack(rk4(_numpy_planar_rates, tuple(np.moveaxis(x, -1, 0)), u, h,
                            substeps), axis=-1)
    check_state_dim(x.shape[-1])
    state = rk4(lambda *v: tuple(np.moveaxis(derivative(np.stack(v[:-1], axis=-1), v[-1]),
                                             -1, 0)),
                tuple(np.moveaxis(x, -1, 0)), u, h, substeps)
    return np.stack(state, axis=-1)


def planar_step(x, u, h=PAPER_STEP, substeps=1):
    """`rk4_step` for one planar state, on Python floats: what a simulator or a closed loop
    advances every sample. Numpy's per-call overhead dominates for a 4-vector (~0.9 ms against
    ~60 us for 10 substeps); the arithmetic is the same and agrees to rounding (a test checks).
    Returns a numpy array; non-finite values propagate (check `in_domain`)."""
    return np.array(rk4(planar_rates, tuple(float(v) for v in x), float(u), h, substeps))


def symbolic_rk4(x, u, dt, substeps):
    """The planar model's RK4 for CasADi expressions (x a 4-vector, u a scalar): the end state
    and every substep's state, as the simulator's `rk4_step` computes them (needs casadi)."""
    import casadi

    def rates(*state):
        return planar_rates(*state, sin=casadi.sin, cos=casadi.cos)
    path = []
    end = rk4(rates, tuple(x[i] for i in range(PLANAR_DIM)), u, dt, substeps, path)
    return casadi.vertcat(*end), [casadi.vertcat(*state) for state in path]


def step(x, u, h=PAPER_STEP, substeps=1):
    """Advance one state by one sample period: `planar_step` for a planar state, `rk4_step`
    otherwise. The simulator and the ROS-free closed loop both step with this."""
    x = np.asarray(x, dtype=float)
    if x.shape == (PLANAR_DIM,):
        with np.errstate(all='ignore'):
            try:
                return planar_step(x, u, h, substeps)
            except (OverflowError, ZeroDivisionError, ValueError):
                return np.full(PLANAR_DIM, np.nan)   # left the domain mid-step
    with np.errstate(all='ignore'):
        return rk4_step(x, u, h, substeps)


def rollout(x0, u_sequence, h=PAPER_STEP, substeps=1):
    """Simulate a batch: x0 (B, n) and u_sequence (B, T) give states (B, T + 1, n).

    A trajectory that leaves the domain turns non-finite from there on; use `in_domain`.
    """
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    u_sequence = np.atleast_2d(np.asarray(u_sequence, dtype=float))
    if u_sequence.shape[0] != x0.shape[0]:
        raise ValueError(f'batch sizes differ: x0 has {x0.shape[0]}, u has {u_sequence.shape[0]}')
    states = np.empty((x0.shape[0], u_sequence.shape[1] + 1, x0.shape[1]))
    states[:, 0] = x0
    with np.errstate(all='ignore'):
        for k in range(u_sequence.shape[1]):
            states[:, k + 1] = rk4_step(states[:, k], u_sequence[:, k], h, substeps)
    return states


def in_domain(x):
    """True where the state is inside the model's domain: finite and tether length l > 0."""
    x = np.asarray(x, dtype=float)
    with np.errstate(invalid='ignore'):
        return np.all(np.isfinite(x), axis=-1) & (x[..., LENGTH_OFFSET] > -1.0)


#: How fast the reel hold (`hold_tension`) stops the tether, 1/tau: l'' = -HOLD_GAIN l'.
HOLD_GAIN = 5.0


def hold_tension(x, gain=HOLD_GAIN, u_max=TENSION_LIMIT):
    """The tension of the reel hold: what a deployer does on its own when its controller stops
    (a reel speed loop to zero, as a brake would): u = l''(u = 0) + gain l', so that
    l'' = -gain l' (the length held once the reel has stopped; theta librates freely at that
    length), clamped to [0, u_max]: a tether cannot push, the reel cannot pull past its limit."""
    x = np.asarray(x, dtype=float)
    free = derivative(x, 0.0)[..., LENGTH_RATE]
    return np.clip(free + gain * x[..., LENGTH_RATE], 0.0, u_max)


#: The longest tether a measured state may have (twice the full length) and its largest swing:
#: past these a message is no TSR state but a wrong one (units, a wrapped angle, a stray test).
PLAUSIBLE_LENGTH = 2.0
PLAUSIBLE_SWING = math.pi


def plausible(x):
    """True where a measured state (..., n) is one a TSR can be in: finite, 0 < l <=
    PLAUSIBLE_LENGTH and |theta| <= PLAUSIBLE_SWING. A controller refuses any other."""
    x = np.asarray(x, dtype=float)
    with np.errstate(invalid='ignore'):
        return (in_domain(x) & (x[..., LENGTH_OFFSET] + 1.0 <= PLAUSIBLE_LENGTH)
                & (np.abs(x[..., THETA]) <= PLAUSIBLE_SWING))


def linearise(x=None, u=EQUILIBRIUM_TENSION):
    """Return the Jacobians (A, B) of the planar model at (x, u): dx' = A dx + B du.

    At the equilibrium A = [[0,1,0,0],[-3,0,0,-2],[0,0,0,1],[0,2,3,0]], B = [0,0,0,-1]^T.
    """
    x = equilibrium_state() if x is None else np.asarray(x, dtype=float)
    if x.shape != (PLANAR_DIM,):
        raise ValueError(f'linearise takes one planar state of shape (4,), got {x.shape}')
    theta, w, x3, v = x[THETA], x[THETA_RATE] + 1.0, x[LENGTH_OFFSET], x[LENGTH_RATE]
    length = x3 + 1.0
    a = np.zeros((PLANAR_DIM, PLANAR_DIM))
    a[THETA, THETA_RATE] = 1.0
    a[THETA_RATE] = [-3.0 * np.cos(2.0 * theta), -2.0 * v / length,
                     2.0 * v * w / length ** 2, -2.0 * w / length]
    a[LENGTH_OFFSET, LENGTH_RATE] = 1.0
    a[LENGTH_RATE] = [-3.0 * length * np.sin(2.0 * theta), 2.0 * length * w,
                      w * w + 3.0 * np.cos(theta) ** 2 - 1.0, 0.0]
    b = np.zeros((PLANAR_DIM, 1))
    b[LENGTH_RATE, 0] = -1.0
    return a, b


def check_state_dim(dim):
    if dim not in (PLANAR_DIM, SPATIAL_DIM):
        raise ValueError(f'a TSR state has {PLANAR_DIM} (planar) or {SPATIAL_DIM} (3-D) '
                         f'components, got {dim}')
