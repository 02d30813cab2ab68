"""SI <-> dimensionless conversion: the one module every node and tool uses.

On the wire everything is SI (REP 103). The dynamics and the learned models work in the paper's
dimensionless variables (arXiv 2307.07713, eq. (1)):

    tau = Omega t                  (t [s], Omega the orbit rate [rad/s])
    l   = length / L               (L the full tether length [m]); x3 = l - 1
    u   = T / (m Omega^2 L)        (T tension [N], m the robot's mass [kg])
    d()/dtau = d()/dt / Omega      so theta' = theta_rate / Omega, l' = length_rate / (L Omega)

Angles are the same in both. The paper's scale: Omega = 1.1804e-3 rad/s, L = 100 km. The paper
does not give m; DEFAULT_MASS is this project's assumption and a parameter everywhere.
"""

from dataclasses import dataclass
import math

import numpy as np

from tsr_sim.dynamics import BETA_RATE, LENGTH_OFFSET, LENGTH_RATE, THETA_RATE

PAPER_ORBIT_RATE = 1.1804e-3   # rad/s
PAPER_TETHER_LENGTH = 100.0e3  # m
DEFAULT_MASS = 20.0            # kg (assumed: the paper is silent)


@dataclass(frozen=True)
class Scale:
    """Physical scale of one TSR: orbit rate [rad/s], full tether length [m], mass [kg]."""

    orbit_rate: float = PAPER_ORBIT_RATE
    tether_length: float = PAPER_TETHER_LENGTH
    mass: float = DEFAULT_MASS

    def __post_init__(self):
        for name in ('orbit_rate', 'tether_length', 'mass'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise ValueError(f'Scale.{name} must be a finite number > 0, got {value!r}')

    @property
    def tension_unit(self):
        """Tension [N] of u = 1: m Omega^2 L."""
        return self.mass * self.orbit_rate ** 2 * self.tether_length

    def tau_to_seconds(self, tau):
        return tau / self.orbit_rate

    def seconds_to_tau(self, seconds):
        return seconds * self.orbit_rate

    def tension_to_u(self, tension):
        """Tension [N] -> dimensionless u."""
        return tension / self.tension_unit

    def u_to_tension(self, u):
        """Dimensionless u -> tension [N]."""
        return u * self.tension_unit

    def state_to_si(self, x):
        """Dimensionless state (..., 4 or 6) -> SI array of the same layout.

        SI layout: [theta rad, theta_rate rad/s, length m, length_rate m/s(, beta rad,
        beta_rate rad/s)]. Note slot 2 holds the length itself, not l - 1.
        """
        si = np.array(x, dtype=float, copy=True)
        si[..., THETA_RATE] *= self.orbit_rate
        si[..., LENGTH_OFFSET] = (si[..., LENGTH_OFFSET] + 1.0) * self.tether_length
        si[..., LENGTH_RATE] *= self.tether_length * self.orbit_rate
        if si.shape[-1] > BETA_RATE:
            si[..., BETA_RATE] *= self.orbit_rate
        return si

    def state_from_si(self, si):
        """SI array (layout of `state_to_si`) -> dimensionless state."""
        x = np.array(si, dtype=float, copy=True)
        x[..., THETA_RATE] /= self.orbit_rate
        x[..., LENGTH_OFFSET] = x[..., LENGTH_OFFSET] / self.tether_length - 1.0
        x[..., LENGTH_RATE] /= self.tether_length * self.orbit_rate
        if x.shape[-1] > BETA_RATE:
            x[..., BETA_RATE] /= self.orbit_rate
        return x
