"""argparse types for the project's tools and your own (the product's commands, the lab): a
bad number or output path is one usage line and exit status 2 before any work starts, not a
traceback after an hour of training.

    from tsr_koopman_ctrl import arguments
    parser.add_argument('--steps', type=arguments.STEPS)
    parser.add_argument('--out', type=arguments.output_dir)
"""

import argparse
import math
import os


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
