"""Plants that differ from the model: the physical causes a data-driven controller must absorb.

Every variant is off by default (`PlantVariant()` is the nominal plant of `dynamics`), and each
stands for one physical cause (docs/plant_variants.md gives the equations and sources):

- Tension actuator (reel motor, brake): gain error ``actuator_gain`` (applied / commanded), bias
  ``actuator_bias`` (dimensionless, in the plant's units) and a first-order lag
  ``actuator_lag`` (time constant in tau): the actuator's tension a follows the command,
  da/dtau = (u_cmd - a) / lag, integrated as one more state inside the same RK4 as the plant.
  A tether cannot push: the applied tension is max(0, gain a + bias).
- Mass: the robot's true mass is the simulator's own `Scale.mass`; a controller converting with
  another mass commands u_cmd m_assumed / m_true without knowing it (a gain error).
- Out of plane: a 6-component initial state starts the 3-D model of `dynamics` with beta, beta';
  the controller measures the planar part.
- Eccentric orbit (changes the dynamics, not the input map): ``eccentricity`` e > 0. The local
  frame turns at the non-uniform rate nu' and the gravity gradient mu / r^3 varies over the
  orbit (Kumar 2006, J. Spacecraft Rockets 43(4); Williams 2008), with tau = n t, n the mean
  motion (the nominal model's Omega), nu the true anomaly::

      nu'    = (1 + e cos nu)^2 / (1 - e^2)^(3/2)
      k      = mu / (r^3 n^2) = (1 + e cos nu)^3 / (1 - e^2)^3
      nu''   = -2 e sin(nu) k
      theta'' = -nu'' - 2 (l' / l) (nu' + theta') - 3 k sin(theta) cos(theta)
      l''     = l [(nu' + theta')^2 + k (3 cos^2 theta - 1)] - u

  theta' stays the rate relative to the local vertical (what is measured). With e = 0, nu' = k =
  1 and nu'' = 0: the nominal plant. Planar only.

The variant's state beyond the mechanical one is [a (actuator tension), nu (true anomaly)].
"""

from dataclasses import dataclass
import math

import numpy as np

from tsr_sim import dynamics


@dataclass(frozen=True)
class PlantVariant:
    """How the true plant differs from the nominal one; every field's default turns it off."""

    actuator_gain: float = 1.0     # applied / commanded tension
    actuator_bias: float = 0.0     # dimensionless tension added after the gain
    actuator_lag: float = 0.0      # actuator time constant [tau]; 0: no lag
    eccentricity: float = 0.0      # orbit eccentricity
    initial_anomaly: float = 0.0   # true anomaly at tau = 0 [rad] (0: perigee)

    def __post_init__(self):
        if not (self.actuator_gain > 0.0 and math.isfinite(self.actuator_gain)):
            raise ValueError(f'actuator_gain must be finite and > 0, got {self.actuator_gain}')
        if not (self.actuator_lag >= 0.0 and math.isfinite(self.actuator_lag)):
            raise ValueError(f'actuator_lag must be finite and >= 0, got {self.actuator_lag}')
        if not math.isfinite(self.actuator_bias):
            raise ValueError(f'actuator_bias must be finite, got {self.actuator_bias}')
        if not 0.0 <= self.eccentricity < 1.0:
            raise ValueError(f'eccentricity must be in [0, 1), got {self.eccentricity}')

    @property
    def nominal(self):
        return self == PlantVariant()


def applied_tension(variant, actuator):
    """The u the dynamics feel for the actuator state `actuator`."""
    return max(0.0, variant.actuator_gain * actuator + variant.actuator_bias)


def orbit_terms(variant, anomaly):
    """(nu', mu / (r^3 n^2), nu'') at the true anomaly `anomaly`: the frame's rate, the gravity
    gradient and the frame's acceleration `dynamics.planar_rates` takes (the circular orbit's
    (1, 1, 0) when e = 0)."""
    e = variant.eccentricity
    if e == 0.0:
        return 1.0, 1.0, 0.0
    one_e = 1.0 + e * math.cos(anomaly)
    gravity = one_e ** 3 / (1.0 - e * e) ** 3
    return one_e ** 2 / (1.0 - e * e) ** 1.5, gravity, -2.0 * e * math.sin(anomaly) * gravity


def augmented_rates(variant, *state):
    """d/dtau of the components of [x (4 or 6), a, nu] under the command u (held), the last
    argument: the plant's own equations (`dynamics.planar_rates`, `dynamics.derivative`) with
    the actuator's tension and the orbit's terms."""
    *x, actuator, anomaly, command = state
    if variant.actuator_lag > 0.0:
        actuator_rate = (command - actuator) / variant.actuator_lag
    else:   # no lag: the actuator is the command itself
        actuator, actuator_rate = command, 0.0
    u = applied_tension(variant, actuator)
    if len(x) != dynamics.PLANAR_DIM:
        return (*dynamics.derivative(np.array(x), u), actuator_rate, 1.0)
    frame_rate, gravity, frame_acceleration = orbit_terms(variant, anomaly)
    return (*dynamics.planar_rates(*x, u, frame_rate=frame_rate, gravity=gravity,
                                   frame_acceleration=frame_acceleration),
            actuator_rate, frame_rate)


def step(variant, state, command, h=dynamics.PAPER_STEP, substeps=10):
    """Advance [x, a, nu] one sample h with the command held: the plant's RK4 (`dynamics.rk4`)
    with `substeps`."""
    state = np.array(state, dtype=float)
    if variant.actuator_lag == 0.0:
        state[-2] = command
    if variant.eccentricity > 0.0 and state.size - 2 != dynamics.PLANAR_DIM:
        raise ValueError('the eccentric-orbit variant is planar only')
    with np.errstate(all='ignore'):
        try:
            return np.array(dynamics.rk4(lambda *v: augmented_rates(variant, *v),
                                         tuple(float(v) for v in state), float(command), h,
                                         substeps))
        except (ValueError, OverflowError, ZeroDivisionError):   # left the domain mid-step
            return np.full_like(state, np.nan)
