"""Node parameters beside the plant's (`plant.PlantSettings`), declared once as schema classes
(`tsr_sim.schema`), ROS-free: the units every node converting them declares, the simulator
node's own, and the process parameters every node gets (`ros_io.run_node`)."""

import dataclasses

from tsr_sim import dynamics
from tsr_sim.schema import LIVE, setting, Settings
from tsr_sim.units import DEFAULT_MASS, PAPER_ORBIT_RATE, PAPER_TETHER_LENGTH
from tsr_sim.wire import STATE_FRAME


@dataclasses.dataclass(frozen=True)
class ScaleSettings(Settings):
    """The units (`units.Scale`): the simulator reads them at start, the controller at
    configure."""

    orbit_rate: float = setting(PAPER_ORBIT_RATE, 'Omega [rad/s]', low=1e-9, high=1.0)
    tether_length: float = setting(PAPER_TETHER_LENGTH, 'full tether length L [m]', low=1e-3,
                                   high=1e9)
    mass: float = setting(DEFAULT_MASS, 'robot mass m [kg]', low=1e-6, high=1e9)


@dataclasses.dataclass(frozen=True)
class SimulatorNodeSettings(Settings):
    """The simulator node's own parameters; a default of None is computed from the units (the
    node passes it). The node declares these, the plant's and the units', nothing else (rclpy
    and `run_node` add their own)."""

    mode: str = setting('lockstep', 'lockstep or timed', choices=('lockstep', 'timed'))
    plant: str = setting('nominal', 'name of the plant variant (recorded in the bag; the '
                         'variant itself is set by the plant parameters, e.g. from '
                         'config/plants/<name>.yaml)')
    max_tension: float = setting(None, f'largest accepted tension [N] (default: u = '
                                 f'{dynamics.TENSION_LIMIT:g})', low=1e-9, high=1e9)
    command_timeout: float = setting(1.0, 'timed mode: wall seconds without a valid command '
                                     'before the plant holds (the reel hold, or safe_tension '
                                     'without one)', low=0.001, high=3600.0, applied=LIVE)
    safe_tension: float = setting(None, 'timed mode, a plant without a reel hold (hold_gain '
                                  '0): tension [N] held when the controller stops or is lost '
                                  '(default: the equilibrium tension u = 3)', low=0.0,
                                  high=1e9, applied=LIVE)
    republish_period: float = setting(0.5, 'lockstep: wall seconds without a command before '
                                      'the state is published again', low=0.01, high=60.0,
                                      applied=LIVE)
    progress_every: int = setting(100, 'log a progress line every N steps (0: never)', low=0,
                                  high=10 ** 9, applied=LIVE)
    wait_for_subscribers: int = setting(0, 'lockstep: publish no state until this many '
                                        'readers of the state topic have matched, at the DDS '
                                        'level (controller, recorder)', low=0, high=1000,
                                        applied=LIVE)
    exit_on_finish: bool = setting(False, 'shut the node down when max_steps is reached or '
                                   'the state leaves the domain', applied=LIVE)
    rate_hz: float = setting(100.0, 'timed: simulation steps per wall second', low=0.01,
                             high=1e5, applied=LIVE)
    clock_start: str = setting('command', "timed: when each run's clock starts (the first and "
                               "after each reset): 'command', at the first command answering "
                               "the run's first state (the plant waits for its controller's "
                               "go, as hardware does); 'matched', once a writer of tension "
                               "commands (a controller) has matched, at the DDS level; 'now', "
                               'at once', choices=('command', 'matched', 'now'))
    frame_id: str = setting(STATE_FRAME, 'frame of the published state (header.frame_id): the '
                            'orbital frame')


@dataclasses.dataclass(frozen=True)
class ProcessSettings(Settings):
    """What every node declares about its process (`ros_io.run_node`): its math threads and
    its executor thread's scheduling. A node in the loop passes its own priority default
    (`ros_io.LOOP_PRIORITY`)."""

    #: One math thread unless told otherwise, so that a node started by hand on a small
    #: machine runs as fast as under a launcher that sets OMP_NUM_THREADS=1 (several BLAS
    #: threads per process stall one another on two cores).
    threads: int = setting(1, 'math (BLAS / OpenMP) threads of this process (0: as the '
                           'environment sets them)', low=0, high=1024)
    thread_priority: int = setting(0, "real-time (SCHED_FIFO) priority of the node's executor "
                                   'thread, 1-99 (0: normal scheduling); needs CAP_SYS_NICE or '
                                   'an rtprio limit, else a warning', low=0, high=99)
