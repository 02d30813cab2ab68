"""Deep Koopman training throughput on this machine, and the time to the shipped model's error.

Figures: trajectories (30-step samples) per second through forward + backward + Adam step at
the shipped model's config and batch size, with all of torch's CPU threads, and the ratio to
one thread measured in the same run (what the machine's other cores buy); the time per epoch
of 4e4 trajectories that implies; and the time to reach the shipped model's validation error,
estimated as (epochs the shipped model needed to reach its best) x (measured epoch time).
"""

import argparse
import os
import sys
import time

import torch

from tsr_koopman_ctrl.learning import dataset as datasets
from tsr_koopman_ctrl.learning import deep_koopman
from tsr_koopman_ctrl.model import DEFAULT_MODEL, model_file, resolve

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--model', default=DEFAULT_MODEL)
    parser.add_argument('--batches', type=int, default=30)
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    _, model_config, meta = model_file.load(resolve(args.model))
    training = model_file.KoopmanConfig.of(model_config, meta).training
    data, _ = datasets.sample(datasets.SamplingConfig(trajectories=training.batch_size * 4))
    x = torch.as_tensor(data.x, dtype=torch.float32)
    u = torch.as_tensor(data.u, dtype=torch.float32)
    net = deep_koopman.DeepKoopman(model_config, x.reshape(-1, 4).mean(0), x.reshape(-1, 4).std(0))
    optimiser = torch.optim.Adam(net.parameters(), lr=training.learning_rate)

    def step(i):
        index = torch.arange(i * training.batch_size, (i + 1) * training.batch_size) % len(x)
        loss, _ = deep_koopman.total_loss(net, x[index], u[index], training)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()

    def throughput(threads):
        """Trajectories per second with `threads` torch CPU threads."""
        torch.set_num_threads(threads)
        for i in range(3):
            step(i)   # warm-up
        start = time.perf_counter()
        for i in range(args.batches):
            step(i)
        return args.batches * training.batch_size / (time.perf_counter() - start)

    threads = torch.get_num_threads()
    single = throughput(1)
    rate = throughput(threads)
    trained = meta['data']['train_trajectories'] * (1 - training.validation_fraction)
    epoch_s = trained / rate
    best_epoch = meta['metrics']['validation_best']['epoch']
    say(f'threads {threads}, batch {training.batch_size}, K {model_config.lift_dim}')
    say(f'training throughput: {rate:,.0f} trajectories/s ({rate * 30:,.0f} state-steps/s)')
    say(f'one thread: {single:,.0f} trajectories/s; ratio {threads} threads / one: '
        f'{rate / single:.2f}')
    say(f'epoch of {trained:,.0f} trajectories: {epoch_s:.1f} s')
    say(f"time to the shipped model's validation error (best at epoch {best_epoch}): "
        f'~{best_epoch * epoch_s / 60:.1f} min (recorded while training: '
        f"{meta['training_seconds'] / 60:.1f} min for {training.epochs} epochs)")
    if 'training_note' in meta:   # e.g. trained partly elsewhere and resumed here
        say(f"note on the recorded time: {meta['training_note']}")
    say.publish()


if __name__ == '__main__':
    main()
