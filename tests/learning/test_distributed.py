"""Data-parallel training (DDP, gloo on the CPU) against one process on the same batches."""

import json
import socket
import time

import numpy as np
import pytest
import torch
from torch import distributed as dist
from torch import multiprocessing

from conftest import tiny_config

from tsr_koopman_ctrl.learning import distributed
from tsr_koopman_ctrl.learning.trainer import Trainer

#: Weights of DDP on two ranks against one process, max |difference| over every tensor. Both
#: take the same steps on the same windows; they differ only in float32 rounding: DDP's
#: all-reduce adds the two ranks' gradients of 16-window means and halves the sum, one process
#: takes the mean over the 32 windows at once. Adam divides each gradient element by its own
#: running magnitude, so an element whose gradient is near zero (the lift's output bias, which
#: the lifted loss barely sees) turns a rounding difference into a visible step. Measured
#: On this test's data (2 epochs of 5 steps): DDP vs one process 8.5e-5, and one
#: process against itself with the two halves of every batch swapped (the same maths, another
#: summation order) 1.3e-4: DDP is at the rounding floor. 5e-4 leaves room for that; rank 0
#: training alone on its half (what DDP without averaging would give) is 1.8e-2 away, checked.
TOLERANCE = 5e-4
WORLD = 2
BLOCK = 16                           # windows per rank per step; global batch 32


@pytest.fixture(scope='module', autouse=True)
def one_thread():
    """One torch thread, as each rank has: the same arithmetic, and on a loaded machine OpenMP
    threads waiting for each other made a 1 s training take a minute."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def free_port():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def config():
    # weight_one_step stays 0: that term normalises by the batch's own std, which is per rank
    # under DDP (like BatchNorm without sync), so it is not a mean over windows.
    return tiny_config().replace(epochs=2, batch_size=WORLD * BLOCK)


def run_ranks(function, args, timeout=120.0):
    """function(rank, *args) in WORLD forked processes. Forked, not spawned: a spawned rank
    would import torch and torch._dynamo (which DDP imports) again, ~5 s here; the children
    set one thread each, as DataLoader workers do after a fork."""
    import torch._dynamo  # noqa: F401  (once here, inherited by the children)
    context = multiprocessing.start_processes(function, args=args, nprocs=WORLD, join=False,
                                              start_method='fork')
    deadline = time.monotonic() + timeout
    while not context.join(timeout=1.0):
        if time.monotonic() > deadline:
            for process in context.processes:
                process.kill()
            raise TimeoutError(f'the {WORLD} ranks did not finish in {timeout} s')


def _train_rank(rank, port, shards, validations, out):
    torch.set_num_threads(1)
    dist.init_process_group('gloo', init_method=f'tcp://127.0.0.1:{port}', rank=rank,
                            world_size=WORLD)
    try:
        trainer = Trainer(config(), progress=False, shuffle=False)
        model = trainer.fit(shards[rank], validation=validations[rank])
        if rank == 0:
            np.savez(out, **model.to_numpy())
            (out.parent / 'history.json').write_text(json.dumps(trainer.history))
    finally:
        dist.destroy_process_group()


def test_ddp_on_two_ranks_trains_to_the_weights_of_one_process(small_data, tmp_path):
    train, val = small_data.subset(np.arange(160)), small_data.subset(np.arange(160, 200))
    # Global batch b is windows 32b .. 32b + 31 for one process; under DDP rank 0 holds the
    # first 16 of them and rank 1 the other 16, in the same order.
    blocks = np.arange(160).reshape(-1, WORLD, BLOCK)
    shards = [train.subset(blocks[:, r].ravel()) for r in range(WORLD)]
    validations = [val.subset(np.arange(20)), val.subset(np.arange(20, 40))]
    out = tmp_path / 'ddp.npz'
    run_ranks(_train_rank, (free_port(), shards, validations, out))

    single = Trainer(config(), progress=False, shuffle=False)
    expected = single.fit(train, validation=val).to_numpy()
    got = dict(np.load(out))
    history = json.loads((tmp_path / 'history.json').read_text())
    assert sorted(got) == sorted(expected)
    difference = max(float(np.abs(got[k] - expected[k]).max()) for k in expected)
    print(f'DDP vs one process: max |weight difference| {difference:.2g}')
    assert difference < TOLERANCE, difference
    alone = Trainer(config().replace(batch_size=BLOCK), progress=False,
                    shuffle=False).fit(shards[0], validation=val).to_numpy()
    apart = max(float(np.abs(alone[k] - got[k]).max()) for k in got)
    assert apart > 10 * TOLERANCE, apart          # the comparison can fail
    # The normalisation is that of all the training states, not of rank 0's shard.
    flat = train.x.reshape(-1, 4)
    np.testing.assert_allclose(got['state_mean'], flat.mean(0), rtol=1e-6)
    np.testing.assert_allclose(got['state_std'], flat.std(0) + 1e-8, rtol=1e-6)
    assert [h['epoch'] for h in history] == [1, 2]
    for mine, theirs in zip(history, single.history):
        assert abs(mine['val_summed_mse'] - theirs['val_summed_mse']) < 1e-4 * theirs[
            'val_summed_mse']
        assert abs(mine['lifted'] - theirs['lifted']) < 1e-4 * theirs['lifted']


def test_a_process_group_of_one_is_the_single_process_path(small_data):
    config_ = tiny_config().replace(epochs=1)
    data = small_data.subset(np.arange(200))
    plain = Trainer(config_, progress=False).fit(data).to_numpy()
    dist.init_process_group('gloo', init_method=f'tcp://127.0.0.1:{free_port()}', rank=0,
                            world_size=1)
    try:
        assert not distributed.current().active
        grouped = Trainer(config_, progress=False).fit(data).to_numpy()
    finally:
        dist.destroy_process_group()
    for name in plain:
        np.testing.assert_array_equal(grouped[name], plain[name])


def test_shards_and_the_global_normalisation_without_a_group():
    context = distributed.Context(rank=1, world_size=3)
    assert distributed.shard(list('abcdefg'), context) == ['b', 'e']
    flat = np.random.default_rng(0).normal(size=(50, 4))
    mean, std = distributed.mean_std(flat)
    np.testing.assert_allclose(mean, flat.mean(0), rtol=1e-12)
    np.testing.assert_allclose(std, flat.std(0), rtol=1e-12)
