"""The simulated plant behind the simulator node, ROS-free: state, step counter, command checks.

The node only converts messages and runs timers; every decision about a command (accept, or
reject and why) and about the state (advance, or halt outside the model's domain) is made here,
so it is tested without ROS and a hardware driver can reuse the same checks.
"""

from dataclasses import dataclass, field
import enum
import math

import numpy as np

from tsr_sim import dynamics
from tsr_sim.units import Scale


class Rejection(enum.Enum):
    """Why a tension command was refused (it never reaches the integrator)."""

    NON_FINITE = 'non_finite'
    NEGATIVE = 'negative'
    OVER_LIMIT = 'over_limit'
    STALE = 'stale'


class Status(enum.IntEnum):
    """Plant status; the values are those of tsr_msgs/SimStatus."""

    RUNNING = 0
    HALTED_OUT_OF_DOMAIN = 1
    FINISHED = 2


@dataclass
class PlantConfig:
    """Settings of the simulated plant. Times in tau, tensions in N."""

    initial_state: np.ndarray = field(
        default_factory=lambda: dynamics.PAPER_INITIAL_STATE.copy())
    step: float = dynamics.PAPER_STEP
    substeps: int = 10
    scale: Scale = field(default_factory=Scale)
    max_tension: float = math.inf         # N; a command above it is rejected
    max_steps: int = 0                    # 0: run for ever
    process_noise_std: tuple = ()         # per state component, dimensionless, added per step
    sensor_noise_std: tuple = ()          # per state component, dimensionless, on measurements
    seed: int = 0

    def __post_init__(self):
        self.initial_state = np.asarray(self.initial_state, dtype=float)
        dynamics.check_state_dim(self.initial_state.shape[-1])
        if self.initial_state.ndim != 1:
            raise ValueError('initial_state must be one state vector')
        if not (self.step > 0.0 and math.isfinite(self.step)):
            raise ValueError(f'step must be finite and > 0, got {self.step}')
        if self.substeps < 1:
            raise ValueError(f'substeps must be >= 1, got {self.substeps}')
        if not self.max_tension > 0.0:
            raise ValueError(f'max_tension must be > 0, got {self.max_tension}')
        for name in ('process_noise_std', 'sensor_noise_std'):
            std = tuple(getattr(self, name))
            if std and (len(std) != self.initial_state.size or min(std) < 0.0):
                raise ValueError(f'{name} needs {self.initial_state.size} values >= 0, '
                                 f'got {std}')
            setattr(self, name, std)


class Plant:
    """A TSR integrated with RK4 that accepts only valid tension commands."""

    def __init__(self, config: PlantConfig):
        self.config = config
        self._rng = np.random.default_rng(config.seed)
        self.counters = {reason: 0 for reason in Rejection}
        self.accepted = 0
        error = self.reset(config.initial_state)
        if error is not None:
            raise ValueError(f'initial_state {config.initial_state.tolist()}: {error}')

    @property
    def tau(self):
        return self.step_index * self.config.step

    def reset(self, state):
        """Restart from `state` (dimensionless) at step 0. Returns an error message or None."""
        state = np.asarray(state, dtype=float)
        if state.shape != self.config.initial_state.shape:
            return f'reset state needs {self.config.initial_state.size} components'
        if not dynamics.in_domain(state):
            return 'reset state is outside the model domain (needs finite values and l > 0)'
        self.state = state.copy()
        self.step_index = 0
        self.status = Status.RUNNING
        self.message = 'running'
        return None

    def check_command(self, tension, step=None):
        """Return the Rejection for a command of `tension` [N] answering `step`, or None."""
        if not math.isfinite(tension):
            return Rejection.NON_FINITE
        if tension < 0.0:
            return Rejection.NEGATIVE
        if tension > self.config.max_tension:
            return Rejection.OVER_LIMIT
        if step is not None and step != self.step_index:
            return Rejection.STALE
        return None

    def accept(self, tension, step=None):
        """Check a command and count it as accepted or rejected; return the Rejection or None."""
        rejection = self.check_command(tension, step)
        if rejection is None:
            self.accepted += 1
        else:
            self.counters[rejection] += 1
        return rejection

    def advance(self, tension):
        """Advance one sample period under `tension` [N], already checked by the caller."""
        if self.status is not Status.RUNNING:
            return
        u = self.config.scale.tension_to_u(tension)
        nxt = dynamics.step(self.state, u, self.config.step, self.config.substeps)
        with np.errstate(all='ignore'):
            nxt = nxt + self._noise(self.config.process_noise_std)
        if not dynamics.in_domain(nxt):
            self.status = Status.HALTED_OUT_OF_DOMAIN
            self.message = (f'state left the model domain at step {self.step_index + 1} '
                            f'(tau {self.tau + self.config.step:.3f}): {nxt.tolist()}; '
                            'integration stopped, reset to continue')
            return
        self.state = nxt
        self.step_index += 1
        if self.config.max_steps and self.step_index >= self.config.max_steps:
            self.status = Status.FINISHED
            self.message = f'finished after {self.step_index} steps (tau {self.tau:.3f})'

    def measure(self):
        """Return the measured state: the true state plus sensor noise, if configured."""
        return self.state + self._noise(self.config.sensor_noise_std)

    def _noise(self, std):
        if not std:
            return 0.0
        return self._rng.normal(0.0, std)
