"""A fixed yardstick for compute figures: one scalar numpy RK4 step of the planar plant with 20
substeps, timed in the same run as what it measures, so a figure survives a noisy machine (a
time is reported as a multiple of it too). The code is frozen here, apart from the product's
`tsr_sim.dynamics.rk4_step` (which got ~3x faster on one state when it was rewritten): a
yardstick must not move when the product does. About 0.25 ms on the project's machine when
idle, 0.9 ms with four other jobs on its two cores.
"""

import time

import numpy as np

STATE = np.array([0.0, 0.0, -0.99, 0.5])


def _derivative(x, u):
    theta, w, v = x[..., 0], x[..., 1] + 1.0, x[..., 3]
    length = x[..., 2] + 1.0
    sin_t, cos_t = np.sin(theta), np.cos(theta)
    theta_acc = -2.0 * (v / length) * w - 3.0 * sin_t * cos_t
    length_acc = length * (w * w + 3.0 * cos_t * cos_t - 1.0) - u
    return np.stack([x[..., 1], theta_acc, v, length_acc], axis=-1)


def step(x=STATE, u=3.0, h=0.01, substeps=20):
    """The yardstick's work: RK4 over h in `substeps` steps, numpy on one 4-vector."""
    x, u, dt = np.asarray(x, dtype=float), np.asarray(u, dtype=float), h / substeps
    for _ in range(substeps):
        k1 = _derivative(x, u)
        k2 = _derivative(x + 0.5 * dt * k1, u)
        k3 = _derivative(x + 0.5 * dt * k2, u)
        k4 = _derivative(x + dt * k3, u)
        x = x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


def seconds(repeats=200, batches=5):
    """Seconds of one yardstick step: the median over `batches` batches."""
    times = []
    for _ in range(batches):
        start = time.perf_counter()
        for _ in range(repeats // batches):
            step()
        times.append((time.perf_counter() - start) / (repeats // batches))
    return float(np.median(times))
