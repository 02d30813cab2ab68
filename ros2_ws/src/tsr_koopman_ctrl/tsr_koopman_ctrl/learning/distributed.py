"""Data-parallel training with PyTorch's own DistributedDataParallel (DDP).

    torchrun --nproc_per_node=2 -m tsr_koopman_ctrl.commands.retrain --bags bags/ --out models/m

torchrun starts one process per rank with RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and
MASTER_PORT set; `start()` joins them into a process group (gloo on the CPU, NCCL when a GPU is
present, one GPU per local rank). Each rank trains on its own shard of the data; DDP averages
the gradients in the backward pass, so every rank takes the same optimiser step and the weights
stay identical. A global batch of B windows is B / W per rank, so with the same windows in each
global batch the step equals one process's up to the float32 summation order of the average.

What this module adds around DDP, and nothing more (no gradient is averaged by hand): the
process group, the shard, `Objective` (the loss as a module's forward, which DDP needs to hook
its reducer into the backward pass) and a few collectives for what is not a gradient: the
normalisation of the training states, the number of batches per epoch (the least over the
ranks: every rank must take the same number of steps, or DDP waits forever) and the validation
error over every rank's windows. Without a process group, or with one of size 1, nothing here
is used and training is the single-process path.
"""

import dataclasses
import os

import numpy as np
import torch
from torch import distributed as dist

from tsr_koopman_ctrl.learning import deep_koopman


@dataclasses.dataclass(frozen=True)
class Context:
    """This process's place in the process group (rank 0 of 1 without one)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def active(self):
        """True when training is data-parallel (more than one rank)."""
        return self.world_size > 1

    @property
    def is_main(self):
        """The rank that prints and writes files."""
        return self.rank == 0

    # What training asks of its ranks. With one rank each is the single-process computation
    # (bit for bit what a run without torchrun does); with more, the collectives below.

    def check(self, train, validation, batch_size):
        """ValueError unless there are windows to train on (on every rank) and to validate
        on, and the batch splits evenly over the ranks."""
        if not self.active:
            if len(train) == 0 or len(validation) == 0:
                raise ValueError(f'{len(train) + len(validation)} trajectories are too few to '
                                 'split off validation')
            return
        sizes = gather((len(train), len(validation)))
        if batch_size % self.world_size:
            raise ValueError(f'batch size {batch_size} does not split evenly over '
                             f'{self.world_size} ranks')
        if any(n == 0 for n, _ in sizes) or sum(v for _, v in sizes) == 0:
            raise ValueError(f'too few windows: training windows per rank '
                             f'{[n for n, _ in sizes]}, validation {sum(v for _, v in sizes)}')

    def objective(self, model, device, training):
        """The training loss of `model` under `training` (a TrainingConfig), (x, u) -> (loss,
        parts): under DDP its wrapped forward, whose backward averages the gradients over the
        ranks."""
        if not self.active:
            return lambda x, u: deep_koopman.total_loss(model, x, u, training)
        return wrap(model, device, training)

    def batches(self, count):
        """Batches per epoch: the least over the ranks (a rank taking fewer steps than the
        others would leave them waiting forever)."""
        return max(1, least(count) if self.active else count)

    def normalisation(self, flat):
        """(mean, std) per column of the training states of every rank together."""
        if not self.active:
            return flat.mean(0), flat.std(0)
        return mean_std(flat)

    def average(self, values, device):
        """A dict of floats averaged over the ranks."""
        return average(values, device) if self.active else values

    def together(self, predicted, truth):
        """(predicted, truth) of every rank's windows, concatenated."""
        if not self.active:
            return predicted, truth
        parts = gather((predicted, truth))
        return (np.concatenate([p for p, _ in parts]), np.concatenate([t for _, t in parts]))


def launched():
    """The Context torchrun describes in the environment, before (or without) a process group:
    lets a command keep ranks other than 0 quiet from its first line."""
    return Context(int(os.environ.get('RANK', 0)), int(os.environ.get('WORLD_SIZE', 1)),
                   int(os.environ.get('LOCAL_RANK', 0)))


def current():
    """The running process group's Context; rank 0 of 1 if there is none."""
    if dist.is_available() and dist.is_initialized():
        rank = dist.get_rank()
        return Context(rank, dist.get_world_size(), int(os.environ.get('LOCAL_RANK', rank)))
    return Context()


def start(backend=None):
    """Join the process group torchrun describes; nothing to do for one process. The backend is
    NCCL when CUDA is available (each local rank on its own GPU), else gloo."""
    context = launched()
    if not context.active or dist.is_initialized():
        return current()
    backend = backend or ('nccl' if torch.cuda.is_available() else 'gloo')
    if backend == 'nccl':
        torch.cuda.set_device(context.local_rank)
    dist.init_process_group(backend)
    return current()


def stop():
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def device_name(context):
    """This rank's device: its own GPU under NCCL, else the CPU."""
    return f'cuda:{context.local_rank}' if torch.cuda.is_available() else 'cpu'


def shard(items, context):
    """Items rank, rank + W, rank + 2W, ...: the part of a list this rank takes."""
    return items[context.rank::context.world_size]


def gather(value):
    """`value` of every rank, in rank order (a picklable object; [value] without a group)."""
    if not current().active:
        return [value]
    values = [None] * dist.get_world_size()
    dist.all_gather_object(values, value)
    return values


def least(value):
    """The smallest of an integer over the ranks."""
    return min(gather(int(value)))


def average(values, device):
    """The mean over the ranks of a dict of floats (one all-reduce)."""
    if not current().active or not values:
        return values
    keys = sorted(values)
    tensor = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=device)
    dist.all_reduce(tensor)
    return dict(zip(keys, (tensor / dist.get_world_size()).tolist()))


def mean_std(flat):
    """Mean and (population) std per column of the rows of every rank together, two-pass in
    float64: the normalisation one process would compute from all the training states."""
    flat = np.asarray(flat, dtype=np.float64)
    parts = gather((flat.sum(axis=0), len(flat)))
    count = sum(n for _, n in parts)
    mean = sum(s for s, _ in parts) / count
    squares = gather(((flat - mean) ** 2).sum(axis=0))
    return mean, np.sqrt(sum(squares) / count)


class Objective(torch.nn.Module):
    """The training loss as a module's forward: DDP averages gradients only for a backward
    that follows its wrapped module's forward."""

    def __init__(self, model, training):
        super().__init__()
        self.model = model
        self.training_config = training

    def forward(self, x, u):
        return deep_koopman.total_loss(self.model, x, u, self.training_config)


def wrap(model, device, training):
    """The model's loss under DDP. Buffers (the state normalisation) never change in training,
    so they are not synchronised at every step; DDP copies rank 0's parameters and buffers once,
    here."""
    from torch.nn.parallel import DistributedDataParallel
    ids = [device.index] if device.type == 'cuda' else None
    return DistributedDataParallel(Objective(model, training), device_ids=ids,
                                   forward_sync_buffers=False)
