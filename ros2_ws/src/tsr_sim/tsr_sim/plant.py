"""The simulated plant behind the simulator node, ROS-free: state, step counter, command checks.

The node only converts messages and runs timers; every decision about a command (accept, or
reject and why) and about the state (advance, or halt outside the model's domain) is made here,
so it is tested without ROS and a hardware driver can reuse the same checks.
"""

import dataclasses
from dataclasses import dataclass, field
import enum
import math

import numpy as np

from tsr_sim import dynamics, variants
from tsr_sim.node_parameters import ScaleSettings, SimulatorNodeSettings
from tsr_sim.schema import did_you_mean, LIVE, parameter_table, setting, Settings
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
    #: |theta| past which the robot is tumbling (`TUMBLING_SWING`): the run halts as it does
    #: when the state leaves the model's domain.
    max_swing: float = dynamics.TUMBLING_SWING
    process_noise_std: tuple = ()         # per state component, dimensionless, added per step
    sensor_noise_std: tuple = ()          # per state component, dimensionless, on measurements
    seed: int = 0
    #: How the true plant differs from the nominal model (off by default; `variants`).
    variant: variants.PlantVariant = field(default_factory=variants.PlantVariant)
    #: The reel hold's gain (`dynamics.hold_tension`), 1/tau: what the plant does on its own
    #: when its controller stops; 0: no hold (the plant flies the last tension it was given).
    hold_gain: float = dynamics.HOLD_GAIN

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
        if not self.max_swing > 0.0:
            raise ValueError(f'max_swing must be > 0, got {self.max_swing}')
        if not (self.hold_gain >= 0.0 and math.isfinite(self.hold_gain)):
            raise ValueError(f'hold_gain must be finite and >= 0, got {self.hold_gain}')
        if self.variant.eccentricity > 0.0 and self.initial_state.size != dynamics.PLANAR_DIM:
            raise ValueError('the eccentric-orbit variant is planar only')
        for name in ('process_noise_std', 'sensor_noise_std'):
            std = tuple(getattr(self, name))
            if std and (len(std) != self.initial_state.size or min(std) < 0.0):
                raise ValueError(f'{name} needs {self.initial_state.size} values >= 0, '
                                 f'got {std}')
            setattr(self, name, std)


@dataclasses.dataclass(frozen=True)
class PlantSettings(Settings):
    """The simulator's plant parameters, declared once (`tsr_sim.schema`): the simulator node
    declares them as ROS parameters; `config_from_parameters` turns a mapping of them (the
    node's values, or a plant file under config/plants/) into a PlantConfig."""

    initial_state: tuple = setting(dynamics.PAPER_INITIAL_STATE.tolist(),
                                   "dimensionless [theta, theta', l-1, l'] (6 values add beta, "
                                   "beta')", fixed_length=False)
    step: float = setting(dynamics.PAPER_STEP, 'sample period h [tau]', low=1e-6, high=10.0)
    substeps: int = setting(10, 'RK4 substeps per sample period', low=1, high=10000)
    max_steps: int = setting(0, 'stop after this many steps (0: never)', low=0, high=10 ** 12,
                             applied=LIVE)
    max_swing: float = setting(dynamics.TUMBLING_SWING, '|theta| past which the robot is '
                               'tumbling: the run halts as when the state leaves the domain '
                               '[rad]', low=0.01, high=100.0)
    process_noise_std: tuple = setting([0.0], 'dimensionless std per state component, added '
                                       'per step ([0.0]: none)', fixed_length=False)
    sensor_noise_std: tuple = setting([0.0], 'dimensionless std per component of the '
                                      'published state ([0.0]: none)', fixed_length=False)
    seed: int = setting(0, 'noise seed', low=0, high=2 ** 31 - 1)
    actuator_gain: float = setting(1.0, 'tension actuator: applied / commanded tension',
                                   low=1e-3, high=100.0)
    actuator_bias: float = setting(0.0, 'tension actuator: bias added to the applied tension '
                                   '[N]', low=-1e6, high=1e6)
    actuator_lag: float = setting(0.0, 'tension actuator: first-order time constant [tau] (0: '
                                  'none)', low=0.0, high=100.0)
    eccentricity: float = setting(0.0, 'orbit eccentricity (0: circular, the nominal model)',
                                  low=0.0, high=0.99)
    initial_anomaly: float = setting(0.0, 'true anomaly at the start [rad] (eccentric orbit)',
                                     low=-7.0, high=7.0)
    out_of_plane: bool = setting(False, 'start the 3-D model with initial_beta appended to the '
                                 'state')
    initial_beta: tuple = setting([0.0, 0.0], "out_of_plane: [beta, beta'] at the start (rad, "
                                  'dimensionless rate)')
    hold_gain: float = setting(dynamics.HOLD_GAIN, "the reel hold engaged when the controller "
                               "stops or is lost: l'' = -hold_gain l' (a speed loop to zero, as "
                               'a brake; the tension within [0, max_tension]) [1/tau]; 0: no '
                               'hold, the last tension is held', low=0.0, high=1e3)


#: The plant's parameters as name -> (default, description, low, high), derived from
#: PlantSettings (read-only).
PLANT_PARAMETERS = parameter_table(PlantSettings)
SCALE_PARAMETERS = tuple(field.name for field in dataclasses.fields(ScaleSettings))
#: The simulator node's other parameters as name -> (default, description, low, high), derived
#: from `node_parameters.SimulatorNodeSettings` (read-only); a default of None is computed from
#: the units (the node passes it). The node declares these, PLANT_PARAMETERS and
#: SCALE_PARAMETERS, nothing else (rclpy and `run_node` add their own).
SIMULATOR_PARAMETERS = parameter_table(SimulatorNodeSettings)

#: What a plant file (config/plants/*.yaml, `deploy --plant`, `closed_loop(plant=...)`) may
#: set: the plant, its units, its tension limit and its name.
PLANT_FILE_PARAMETERS = (*PLANT_PARAMETERS, *SCALE_PARAMETERS, 'max_tension', 'plant')


def check_plant_parameter_names(names, source):
    """ValueError naming `source` and the first name that is not a plant parameter (ROS would
    drop a misspelt one without a word), with the closest one if there is one."""
    for name in sorted(set(names) - set(PLANT_FILE_PARAMETERS), key=str):
        raise ValueError(f'{source}: {name!r} is not a plant parameter'
                         f'{did_you_mean(name, PLANT_FILE_PARAMETERS)}')


def config_from_parameters(values, scale=None):
    """A PlantConfig from simulator parameters: any subset of PLANT_PARAMETERS (the defaults for
    the rest), the units (`orbit_rate`, `tether_length`, `mass`: the true plant's, else those of
    `scale`, else the paper's), `max_tension` [N] (default u = TENSION_LIMIT at those units),
    and `plant` (the variant's name, not part of the config)."""
    check_plant_parameter_names(values, 'plant parameters')
    scale = scale or Scale()
    scale = Scale(**{name: values.get(name, getattr(scale, name)) for name in SCALE_PARAMETERS})
    v = {name: values.get(name, spec[0]) for name, spec in PLANT_PARAMETERS.items()}
    initial = list(v['initial_state'])
    if v['out_of_plane']:
        initial = initial[:dynamics.PLANAR_DIM] + list(v['initial_beta'])
    variant = variants.PlantVariant(
        actuator_gain=v['actuator_gain'], actuator_bias=scale.tension_to_u(v['actuator_bias']),
        actuator_lag=v['actuator_lag'], eccentricity=v['eccentricity'],
        initial_anomaly=v['initial_anomaly'])

    def noise(std):
        return tuple(std) if any(std) else ()
    return PlantConfig(
        initial_state=initial, step=v['step'], substeps=v['substeps'], scale=scale,
        max_tension=values.get('max_tension', scale.u_to_tension(dynamics.TENSION_LIMIT)),
        max_steps=v['max_steps'], max_swing=v['max_swing'],
        process_noise_std=noise(v['process_noise_std']),
        sensor_noise_std=noise(v['sensor_noise_std']), seed=v['seed'], variant=variant,
        hold_gain=v['hold_gain'])


class Plant:
    """A TSR integrated with RK4 that accepts only valid tension commands."""

    def __init__(self, config: PlantConfig):
        self.config = config
        self._rng = np.random.default_rng(config.seed)
        self.counters = {reason: 0 for reason in Rejection}
        self.accepted = 0
        self.run = -1          # the first reset starts run 0
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
        if abs(state[dynamics.THETA]) > self.config.max_swing:
            return (f'reset state swings past max_swing {self.config.max_swing:g} rad '
                    '(tumbling)')
        self.state = state.copy()
        self.actuator = None   # the actuator starts at rest on the first command
        self.anomaly = self.config.variant.initial_anomaly
        self.step_index = 0
        self.run += 1
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

    def hold_tension(self):
        """The tension [N] the reel hold applies now (`dynamics.hold_tension` on the true
        state, within [0, max_tension]), or None for a plant without a hold."""
        if not self.config.hold_gain:
            return None
        scale = self.config.scale
        u_max = scale.tension_to_u(self.config.max_tension)
        return scale.u_to_tension(float(dynamics.hold_tension(
            self.state, self.config.hold_gain, u_max if math.isfinite(u_max) else np.inf)))

    def advance(self, tension, hold=False):
        """Advance one sample period under `tension` [N], already checked by the caller; with
        `hold`, under the reel hold instead (`hold_tension`, evaluated at the sample's start),
        which acts on the tether directly: the actuator's gain, bias and lag are the tension
        controller's, not the hold's."""
        if self.status is not Status.RUNNING:
            return
        variant = self.config.variant
        held = self.hold_tension() if hold else None
        if held is not None:
            tension = held
            variant = dataclasses.replace(variant, actuator_gain=1.0, actuator_bias=0.0,
                                          actuator_lag=0.0)
        u = self.config.scale.tension_to_u(tension)
        if variant.nominal:
            nxt = dynamics.step(self.state, u, self.config.step, self.config.substeps)
        else:
            actuator = u if self.actuator is None else self.actuator
            augmented = variants.step(variant, np.r_[self.state, actuator, self.anomaly], u,
                                      self.config.step, self.config.substeps)
            nxt, (actuator, anomaly) = augmented[:-2], augmented[-2:]
        with np.errstate(all='ignore'):
            nxt = nxt + self._noise(self.config.process_noise_std)
        where = f'at step {self.step_index + 1} (tau {self.tau + self.config.step:.3f})'
        if not dynamics.in_domain(nxt):
            self.halt(f'state left the model domain {where}: {nxt.tolist()}')
            return
        if nxt[dynamics.LENGTH_OFFSET] + 1.0 > dynamics.PLAUSIBLE_LENGTH:
            self.halt(f'the tether paid out past {dynamics.PLAUSIBLE_LENGTH:g} times its length '
                      f'{where}: {nxt.tolist()}')
            return
        if abs(nxt[dynamics.THETA]) > self.config.max_swing:
            self.halt(f'tumbling {where}: |theta| = {abs(nxt[dynamics.THETA]):.3f} rad past '
                      f'max_swing {self.config.max_swing:g}')
            return
        self.state = nxt
        if not variant.nominal:
            self.actuator, self.anomaly = actuator, anomaly
        self.step_index += 1
        if self.config.max_steps and self.step_index >= self.config.max_steps:
            self.status = Status.FINISHED
            self.message = f'finished after {self.step_index} steps (tau {self.tau:.3f})'

    def halt(self, what):
        self.status = Status.HALTED_OUT_OF_DOMAIN
        self.message = f'{what}; integration stopped, reset to continue'

    def measure(self):
        """Return the measured state: the true state plus sensor noise, if configured."""
        return self.state + self._noise(self.config.sensor_noise_std)

    def _noise(self, std):
        if not std:
            return 0.0
        return self._rng.normal(0.0, std)


def plant_file(name):
    """Path of a plant variant file: a YAML path as given, or a variant's name under the
    installed share/tsr_sim/config/plants (ValueError naming the paths tried)."""
    import os
    if os.path.isfile(name):
        return name
    tried = [os.path.abspath(name)]
    from tsr_sim.share import NOT_SOURCED, share_directory
    share = share_directory('tsr_sim')
    if share is None:
        tried.append(f'share/tsr_sim/config/plants ({NOT_SOURCED})')
    else:
        plants = os.path.join(share, 'config', 'plants')
        candidate = os.path.join(plants, f'{name}.yaml')
        if os.path.isfile(candidate):
            return candidate
        tried.append(candidate)
        known = sorted(f[:-5] for f in os.listdir(plants) if f.endswith('.yaml'))
        tried.append(f'the variants are {", ".join(known)}')
    raise ValueError(f'no plant variant {name!r} (tried {", ".join(tried)})')


def plant_parameters(name):
    """The plant parameters of a plant variant file (its ros__parameters); ValueError for
    a name that is not a plant parameter."""
    from tsr_sim.parameter_file import node_parameters
    path = plant_file(name)
    parameters = node_parameters(path)
    check_plant_parameter_names(parameters, path)
    check_plant_parameter_values(parameters, path)
    return parameters


def check_plant_parameter_values(values, source):
    """ValueError naming `source` for a value the simulator node would refuse at start (out of
    its declared range, or a plant the config cannot be built from), so a tool can say it
    before any process starts."""
    import numbers
    for name, value in values.items():
        spec = PLANT_PARAMETERS.get(name) or SIMULATOR_PARAMETERS.get(name)
        if spec is None:
            continue
        default, _, low, high = spec
        if low is None and high is None:
            continue
        integer = isinstance(default, int) and not isinstance(default, bool)
        if (not isinstance(value, numbers.Integral if integer else numbers.Real)
                or isinstance(value, bool)):
            raise ValueError(f"{source}: {name} must be {'an integer' if integer else 'a number'}"
                             f', got {value!r}')
        if not low <= value <= high:
            raise ValueError(f'{source}: {name} must be in [{low:g}, {high:g}], got {value!r}')
    try:
        config_from_parameters(values)
    except (ValueError, TypeError) as error:
        raise ValueError(f'{source}: {error}') from None
