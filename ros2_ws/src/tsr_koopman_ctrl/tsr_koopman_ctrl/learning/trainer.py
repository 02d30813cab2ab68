"""Training of the deep Koopman model: `Trainer.fit` and the model file it writes.

Each epoch prints the loss terms and the validation 30-step error; the best epoch so far is kept
and is the model returned and saved; ``<out>/checkpoint.pt`` after every epoch lets a run
resume after an interruption. CPU by default, CUDA when present. The command line is
`tsr_koopman_ctrl.commands.train`.

Fine-tuning: `fit(data, init=tensors)` starts from an existing model's weights and keeps its
state normalisation. Data-parallel: inside a torch.distributed process group of more than one
rank (`learning.distributed`), `fit` trains this rank's shard under DistributedDataParallel
with `batch_size / world size` windows per rank, and only rank 0 prints and writes the
checkpoint; without one (or with one rank) it is the single-process path, unchanged.

`Trainer(..., kind=kinds.Block())` trains a `block_koopman.BlockKoopman` (observables stable
by construction) instead of the dense model (`kinds.Dense()`, the default); whatever the kind,
what it saves is an ordinary model file.
"""

import dataclasses
import json
import pathlib
import platform
import sys

import numpy as np
import torch
from tqdm import tqdm

from tsr_koopman_ctrl.learning import distributed, errors, kinds
from tsr_koopman_ctrl.model import coordinates, lifted, model_file

CHECKPOINT = 'checkpoint.pt'
#: Under DDP rank r shuffles its shard with seed + epoch + r * this (rank 0: as one process).
RANK_SEED_STRIDE = 1_000_003


def pick_device(name=None):
    if name:
        return torch.device(name)
    return torch.device('cuda' if torch.cuda.is_available() else 'cpu')


def to_tensors(data, device):
    return (torch.as_tensor(data.x, dtype=torch.float32, device=device),
            torch.as_tensor(data.u, dtype=torch.float32, device=device))


def predict_states(model, data, device, batch=4096):
    """States predicted by a torch model for every trajectory of `data`, as numpy."""
    x, u = to_tensors(data, device)
    with torch.no_grad():
        parts = [model.predict(x[i:i + batch, 0], u[i:i + batch]).cpu().numpy()
                 for i in range(0, len(x), batch)]
    return np.concatenate(parts)


def evaluate(model, data, device, context=None):
    """multistep_errors of `model` on `data`; under DDP (`context`), on the windows of every
    rank together (each rank passes its own)."""
    context = context or distributed.Context()
    predicted = predict_states(model, data, device) if len(data) else data.x
    return errors.multistep_errors(*context.together(predicted, data.x))


class Trainer:
    """fit() a DeepKoopman on a Dataset; keeps the best epoch by validation 30-step error.

    `shuffle=False` takes the windows in their order every epoch (batches are consecutive
    slices): for a data order fixed by the caller, as the DDP equivalence test needs.
    """

    def __init__(self, config, out_dir=None, device=None, progress=True, shuffle=True,
                 kind=None):
        self.config = config        # a KoopmanConfig: the model and its training
        self.kind = kind or kinds.Dense()
        self.out_dir = pathlib.Path(out_dir) if out_dir else None
        self.context = distributed.current()
        if self.context.active and device in (None, 'cuda'):
            device = distributed.device_name(self.context)   # each rank its own GPU
        self.device = pick_device(device)
        self.progress = progress and self.context.is_main
        self.shuffle = shuffle
        self.history = []

    def fit(self, data, resume=False, init=None, validation=None):
        """Train on `data`; returns the best epoch's model. `init`: tensors of a model to start
        from (`model_file.load`), normalisation included (fine-tuning); without it a new model
        normalised on the training states. `validation`: the windows the best epoch is chosen
        on, instead of a `validation_fraction` split of `data`. Under DDP `data` and
        `validation` are this rank's shard."""
        training, context = self.config.training, self.context
        torch.manual_seed(training.seed)
        if validation is None:
            train, val = data.split(1.0 - training.validation_fraction, seed=training.seed)
        else:
            train, val = data, validation
        context.check(train, val, training.batch_size)
        per_rank = training.batch_size // context.world_size
        # An init keeps its own normalisation; a new model is normalised on the training states.
        mean, std = (None, None) if init is not None else self.normalisation(train)
        model = self.kind.build(self.config.model, init, mean, std)
        model.to(self.device)
        objective = context.objective(model, self.device, training)
        optimiser = torch.optim.Adam(model.parameters(), lr=training.learning_rate)
        batches = context.batches(len(train) // per_rank)
        scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
            optimiser, T_max=training.epochs * batches, eta_min=training.final_learning_rate)
        start_epoch, self.best = 0, {'summed_mse': np.inf}
        self.best_tensors = model.to_numpy()
        if init is not None:
            # The init is epoch 0: fine-tuning that only makes the validation error worse
            # returns the init unchanged.
            model.eval()
            self.best = {**evaluate(model, val, self.device, context), 'epoch': 0}
            model.train()
            if self.progress:
                print(f"init: val 30-step summed MSE {self.best['summed_mse']:.3e}", flush=True)
        if resume:
            start_epoch = self.restore(model, optimiser, scheduler, batches)
        x, u = to_tensors(train, self.device)
        generator = torch.Generator().manual_seed(
            training.seed + start_epoch + RANK_SEED_STRIDE * context.rank)
        for epoch in range(start_epoch, training.epochs):
            order = (torch.randperm(len(x), generator=generator) if self.shuffle
                     else torch.arange(len(x)))
            bar = tqdm(range(batches), desc=f'epoch {epoch + 1}/{training.epochs}',
                       disable=not self.progress, leave=False, file=sys.stdout)
            sums = {}
            for b in bar:
                index = order[b * per_rank:(b + 1) * per_rank]
                loss, parts = objective(x[index], u[index])
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                scheduler.step()
                for key, value in parts.items():
                    sums[key] = sums.get(key, 0.0) + value
                bar.set_postfix(loss=f'{loss.item():.4g}')
            means = {k: v / batches for k, v in sums.items()}
            self.end_epoch(epoch, model, val, context.average(means, self.device))
            self.save_checkpoint(epoch + 1, model, optimiser, scheduler)
        model.load_state_dict({k: torch.as_tensor(v) for k, v in self.best_tensors.items()})
        return model

    def normalisation(self, train):
        """(mean, std) of the training states in the model's coordinates (over every rank
        under DDP)."""
        flat = coordinates.to_model(train.x.reshape(-1, train.x.shape[2]),
                                    self.config.model.momentum_power)
        mean, std = self.context.normalisation(flat)
        return mean, std + 1e-8

    def end_epoch(self, epoch, model, val, train_losses):
        model.eval()
        metrics = evaluate(model, val, self.device, self.context)
        model.train()
        record = {'epoch': epoch + 1, **train_losses, 'val_summed_mse': metrics['summed_mse']}
        improved = metrics['summed_mse'] < self.best['summed_mse']
        if improved:
            self.best = {**metrics, 'epoch': epoch + 1}
            self.best_tensors = model.to_numpy()
        self.history.append(record)
        if self.progress:
            print(f"epoch {epoch + 1:3d}: rec {train_losses['reconstruction']:.3e} "
                  f"lift {train_losses['lifted']:.3e} ctrb {train_losses['controllability']:.3e}"
                  f" eq {train_losses['equilibrium']:.2e} step {train_losses['one_step']:.2e}"
                  f"  val 30-step summed MSE {metrics['summed_mse']:.3e}"
                  + ('  (best)' if improved else ''), flush=True)

    def save_checkpoint(self, epochs_done, model, optimiser, scheduler):
        if self.out_dir is None or not self.context.is_main:
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        state = {'epochs_done': epochs_done, 'model': model.state_dict(),
                 'optimiser': optimiser.state_dict(), 'scheduler': scheduler.state_dict(),
                 'best_tensors': {k: torch.as_tensor(v) for k, v in self.best_tensors.items()},
                 'best': json.dumps(self.best), 'history': json.dumps(self.history),
                 'config': json.dumps(self.config.as_dict())}
        partial = self.out_dir / (CHECKPOINT + '.partial')
        torch.save(state, partial)
        partial.replace(self.out_dir / CHECKPOINT)

    def restore(self, model, optimiser, scheduler, batches):
        path = self.out_dir / CHECKPOINT if self.out_dir else None
        if path is None or not path.exists():
            raise ValueError(f'cannot resume: no {path}')
        try:
            state = torch.load(path, map_location=self.device, weights_only=True)
            saved = json.loads(state['config'])
        except Exception as error:   # torch raises many kinds for a damaged file
            raise ValueError(f'cannot resume: {path} is damaged or not a checkpoint '
                             f'({type(error).__name__})')
        current = json.loads(json.dumps(self.config.as_dict()))
        # More epochs than before is allowed: that continues training.
        differ = sorted(k for k in current if saved.get(k) != current[k] and k != 'epochs')
        if differ:
            raise ValueError(f'cannot resume: {path} was trained with different {differ}')
        model.load_state_dict(state['model'])
        optimiser.load_state_dict(state['optimiser'])
        scheduler.load_state_dict(state['scheduler'])
        # the (possibly longer) new schedule
        scheduler.T_max = self.config.training.epochs * batches
        self.best_tensors = {k: v.cpu().numpy() for k, v in state['best_tensors'].items()}
        self.best = json.loads(state['best'])
        self.history = json.loads(state['history'])
        if self.progress:
            print(f"resuming {path} after epoch {state['epochs_done']}", flush=True)
        return int(state['epochs_done'])


def versions():
    import safetensors
    return {'python': platform.python_version(), 'numpy': np.__version__,
            'torch': torch.__version__, 'safetensors': safetensors.__version__}


def save_model(out_dir, model, config, trainer, train_data, test_data, seconds, command,
               extra=None, envelope=None):
    """Write the model (`config`: its KoopmanConfig) with its test metrics, controllability
    rank and provenance; `extra`: more metadata (a dict merged in); `envelope`: the box of its
    training states (`dataset.envelope`), which the supervisor checks states against.
    `train_data` needs only `provenance` and len()."""
    test = evaluate(model, test_data, trainer.device)
    tensors = trainer.kind.tensors(model)
    metadata = {
        'metrics': {'test': test, 'validation_best': trainer.best,
                    'controllability_rank': lifted.controllability_rank(
                        tensors['A'], tensors['B']),
                    'lifted_dim': config.model.lifted_dim},
        'training': dataclasses.asdict(config.training),
        'history': trainer.history,
        'data': {'train': train_data.provenance, 'test': test_data.provenance,
                 'train_trajectories': len(train_data), 'test_trajectories': len(test_data)},
        'training_seconds': round(seconds, 1), 'device': str(trainer.device),
        'command': command, 'versions': versions(), **(extra or {})}
    if envelope is not None:
        metadata['envelope'] = envelope
    record = trainer.kind.record(model)
    if record is not None:      # how the kind was built, so a fine-tune builds it again
        metadata['structure'] = record
    model_file.save(out_dir, tensors, config.model, metadata)
    return metadata
