"""Tension controllers behind one interface, ROS-free. All work in the paper's dimensionless
variables: `compute(x)` takes the planar state [theta, theta', l-1, l'] and returns u.

The node (and any closed loop) passes u through `TensionLimiter`, the single output clamp.
"""

import math

import numpy as np
import scipy.linalg

from tsr_sim import dynamics


class LinearisedLqr:
    """Linearised full-state tension law (Pradeep 1997 type): u = u_eq - K x.

    K is the continuous-time LQR gain of the linearisation at x = 0, u = 3 with weights Q, R.
    Q = I4, R = 1 settles the paper's deployment in ~9.1 tau with theta in [-0.80, 0.02]
    (../shared/TSR_PHYSICS.md; test_controllers.py checks it).
    """

    name = 'linear_lqr'

    def __init__(self, q=None, r=1.0):
        a, b = dynamics.linearise()
        q = np.eye(dynamics.PLANAR_DIM) if q is None else np.asarray(q, dtype=float)
        r = np.atleast_2d(float(r))
        p = scipy.linalg.solve_continuous_are(a, b, q, r)
        self.gain = np.linalg.solve(r, b.T @ p)[0]

    def reset(self):
        pass

    def compute(self, x):
        planar = np.asarray(x)[:dynamics.PLANAR_DIM]
        return dynamics.EQUILIBRIUM_TENSION - float(self.gain @ planar)


CONTROLLERS = {LinearisedLqr.name: LinearisedLqr}


def make_controller(name, **options):
    try:
        cls = CONTROLLERS[name]
    except KeyError:
        raise ValueError(f'unknown controller {name!r}; choose from {sorted(CONTROLLERS)}')
    return cls(**options)


class TensionLimiter:
    """Clamp u into [0, u_max] (a tether cannot push) and count how often it had to."""

    def __init__(self, u_max):
        if not (math.isfinite(u_max) and u_max > 0.0):
            raise ValueError(f'u_max must be finite and > 0, got {u_max}')
        self.u_max = u_max
        self.clamped = 0

    def __call__(self, u):
        if not math.isfinite(u):
            raise ValueError(f'controller produced a non-finite tension {u}')
        limited = min(max(u, 0.0), self.u_max)
        self.clamped += limited != u
        return limited


def closed_loop(controller, x0, steps, h=dynamics.PAPER_STEP, substeps=10, u_max=5.0):
    """Run controller on the dynamics module: returns states (steps+1, n) and tensions (steps,)."""
    limiter = TensionLimiter(u_max)
    controller.reset()
    states = [np.asarray(x0, dtype=float)]
    tensions = []
    for _ in range(steps):
        u = limiter(controller.compute(states[-1]))
        tensions.append(u)
        states.append(dynamics.rk4_step(states[-1], u, h, substeps))
    return np.array(states), np.array(tensions)
