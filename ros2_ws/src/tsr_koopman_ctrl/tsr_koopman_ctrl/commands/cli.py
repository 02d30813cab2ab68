"""argparse types shared by the tools: a bad number or output path is one usage line and exit
status 2 before any work starts, not a traceback after an hour of training."""

import argparse
import math
import os

from tsr_sim import dynamics
from tsr_sim.units import DEFAULT_MASS, PAPER_ORBIT_RATE, PAPER_TETHER_LENGTH, Scale


def integer(minimum=None, maximum=None):
    """An int in [minimum, maximum] (either bound may be None)."""
    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not an integer') from None
        check_range(value, minimum, maximum)
        return value
    return parse


def number(minimum=None, maximum=None, above=None):
    """A finite float in [minimum, maximum], and > above where given."""
    def parse(text):
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f'{text!r} is not a finite number')
        if above is not None and value <= above:
            raise argparse.ArgumentTypeError(f'{value:g} must be > {above:g}')
        check_range(value, minimum, maximum)
        return value
    return parse


def check_range(value, minimum, maximum):
    if minimum is not None and value < minimum:
        raise argparse.ArgumentTypeError(f'{value:g} must be >= {minimum:g}')
    if maximum is not None and value > maximum:
        raise argparse.ArgumentTypeError(f'{value:g} must be <= {maximum:g}')


def output_dir(text):
    """A directory to write in: a directory, or absent below one this user can write in (it is
    created later), never a file or a path through one."""
    if os.path.exists(text) and not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f'{text} exists and is not a directory')
    existing = os.path.abspath(text)
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise argparse.ArgumentTypeError(f'{text}: {existing} is not a directory')
    if not os.access(existing, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f'{text}: {existing} is not writable')
    return text


def model_dir(text):
    """A model directory to write: an output directory that is not a bag's (rosbag2 layout:
    metadata.yaml beside the .mcap files)."""
    if os.path.isfile(os.path.join(output_dir(text), 'metadata.yaml')):
        raise argparse.ArgumentTypeError(f'{text} is a bag directory, not a model directory')
    return text


#: Exit status of a tool stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
INTERRUPTED_STATUS = 130


def add_overwrite(parser):
    parser.add_argument('--overwrite', action='store_true',
                        help='replace the model --out already holds (refused without it)')


def torch_device(text):
    """A torch device this machine has (cpu, cuda, cuda:1, ...)."""
    import torch
    try:
        device = torch.device(text)
    except RuntimeError:
        device = None
    if device is None or device.type not in ('cpu', 'cuda') or (
            device.type == 'cpu' and device.index not in (None, 0)):
        raise argparse.ArgumentTypeError(f'{text!r} is not a torch device this project '
                                         'trains on (cpu, cuda, cuda:0, ...)')
    if device.type == 'cuda' and (device.index or 0) >= torch.cuda.device_count():
        raise argparse.ArgumentTypeError(f'{text}: torch sees {torch.cuda.device_count()} '
                                         'CUDA devices here')
    return text


#: ROS_DOMAIN_ID: DDS's port formula allows 0..232; 0..101 also stays clear of Linux's
#: ephemeral ports (the ROS 2 docs, "The ROS_DOMAIN_ID").
DOMAIN_ID = integer(0, 232)
#: numpy's and Optuna's seeds are unsigned 32-bit.
SEED = integer(0, 2 ** 32 - 1)
STEPS = integer(1)


def add_loop_reading(parser):
    """The options that read a bag the simulator did not describe (no RunInfo: hardware's, or
    another recorder's): its units, its sample period, how its commands apply. A bag with the
    simulator's RunInfo is read with the simulator's own units and period."""
    group = parser.add_argument_group(
        'bags without a simulator RunInfo (hardware, another recorder)',
        'A bag needs only tsr/state and tsr/tension_cmd. Units and sample period come from '
        "the simulator's RunInfo when the bag has one, else from these options.")
    paper_h = Scale().tau_to_seconds(dynamics.PAPER_STEP)
    group.add_argument('--sample-period', type=number(above=0), metavar='SECONDS',
                       help="sample period (default: the median interval of the states' "
                       f'header stamps per step; the paper\'s 0.01 tau is {paper_h:.4g} s at '
                       'the default orbit rate)')
    group.add_argument('--orbit-rate', type=number(above=0), metavar='RAD_PER_S',
                       help=f"orbit rate Omega (default: the paper's {PAPER_ORBIT_RATE:g})")
    group.add_argument('--tether-length', type=number(above=0), metavar='METRES',
                       help=f"full tether length L (default: the paper's {PAPER_TETHER_LENGTH:g})")
    group.add_argument('--mass', type=number(above=0), metavar='KG',
                       help=f'robot mass m (default: {DEFAULT_MASS:g}, the paper gives none)')
    group.add_argument('--match-commands', choices=('step', 'time'),
                       help="how a command applies: 'step', to the state whose step it carries "
                       "(a lockstep simulator); 'time', from when it was received until the "
                       "next command (zero-order hold: a timed simulator, hardware). Default: "
                       "'step' if the simulator's RunInfo says lockstep, else 'time'")


def loop_reading(args):
    """The options `add_loop_reading` added, as `bag.read_runs` takes them."""
    from tsr_koopman_ctrl.bag.tsr_loop import reading_options
    return reading_options(args.sample_period, args.orbit_rate, args.tether_length, args.mass,
                           args.match_commands)
