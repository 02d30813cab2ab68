"""Train a deep Koopman model: ``python -m tsr_koopman_ctrl.commands.train --out models/NAME``.

Data: sampled with the paper's settings (``--trajectories``, ``--data-seed``) and/or read from
dataset files (``--data FILE``, repeatable). A validation split is held out of training; a
separate test set (another seed, never trained on) gives the metrics stored with the model.
Each epoch prints the loss terms and the validation 30-step error; the best epoch is the saved
model; ``<out>/checkpoint.pt`` lets ``--resume`` carry on after an interruption.

``--init DIR`` fine-tunes a model (its weights, normalisation and config; the flags given
override the config) as the kind it was trained as (`learning.kinds`). ``--structure block``
trains `learning.block_koopman.BlockKoopman`, whose observables are stable by construction (what
koopman_lqr needs; models/README.md, koopman_block); the file it writes is an ordinary model
file.
"""

import argparse
import os
import sys
import time

import torch
from tsr_koopman_ctrl.learning import data, dataset as datasets, kinds
from tsr_koopman_ctrl.learning.block_koopman import BlockStructure
from tsr_koopman_ctrl.learning.trainer import CHECKPOINT, save_model, Trainer
from tsr_koopman_ctrl.model import model_file, shipped
from tsr_koopman_ctrl.commands import cli


def load_data(args):
    """The training data the flags ask for (`learning.data.training_data`)."""
    extra = {name: getattr(args, name.replace('-', '_')) for name, *_ in data.EXTRA_BOXES}
    return data.training_data(args.data, args.trajectories, args.data_seed,
                              log=lambda line: print(line, flush=True), **extra)


def config_from_args(args, base=None):
    """The defaults (or `base`, an init's KoopmanConfig) with the flags given."""
    overrides = {'epochs': args.epochs, 'weight_equilibrium': args.weight_equilibrium,
                 'weight_one_step': args.weight_one_step,
                 'momentum_power': args.momentum_power, 'weight_physical': args.weight_physical,
                 'anchor_equilibrium': args.anchor_equilibrium or None,
                 'lift_dim': args.lift_dim, 'hidden': args.hidden, 'layers': args.layers,
                 'input_hidden': args.input_hidden, 'input_layers': args.input_layers,
                 'seed': args.seed, 'batch_size': args.batch_size,
                 'learning_rate': args.learning_rate}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    return (base or model_file.KoopmanConfig()).replace(**overrides)


def kind_from_args(args, init_metadata=None):
    """The model kind to train: --structure's, else the init's own (`kinds.from_metadata`),
    else dense."""
    if args.structure == 'block':
        return kinds.Block(BlockStructure(
            real_modes=args.real_modes, radius=args.radius, margin=args.margin,
            flat=not args.no_flat, observable_input=args.observable_input))
    if args.structure == 'dense' or init_metadata is None:
        return kinds.Dense()
    return kinds.from_metadata(init_metadata)


def parser():
    p = argparse.ArgumentParser(prog='train', description=__doc__.split('\n\n')[0])
    p.add_argument('--out', required=True, type=cli.model_dir, help='model directory to write')
    cli.add_overwrite(p)
    p.add_argument('--data', action='append', default=[], help='dataset file (repeatable)')
    p.add_argument('--trajectories', type=int, default=40_000,
                   help='trajectories to sample with the paper settings (0: none)')
    p.add_argument('--equilibrium-trajectories', type=int, default=0,
                   help='extra trajectories from a box around x = 0 (not in the paper)')
    p.add_argument('--retrieval-trajectories', type=int, default=0,
                   help="extra trajectories with the tether reeled in, l' < 0 (not in the "
                   'paper)')
    p.add_argument('--held-tension-trajectories', type=int, default=0,
                   help='extra trajectories from the Table-1 box with tensions held for 10 '
                   'steps, two in three at 0 or 5 (not in the paper)')
    p.add_argument('--short-tether-trajectories', type=int, default=0,
                   help='extra trajectories with l < 0.15 and |l\'| <= 0.3, tensions held as '
                   'above (not in the paper)')
    p.add_argument('--weight-equilibrium', type=float,
                   help='weight of the equilibrium drift loss (not in the paper; default 0)')
    p.add_argument('--weight-one-step', type=float,
                   help='weight of the one-step error from every measured state (not in the '
                   'paper; default 0)')
    p.add_argument('--momentum-power', type=cli.number(minimum=0.0, maximum=2.0),
                   help="p: the model evolves l^p (1 + theta') in place of theta' (not in the "
                   'paper; default 0, the physical state; model/coordinates.py)')
    p.add_argument('--weight-physical', type=cli.number(minimum=0.0),
                   help='weight of the reconstruction loss on the physical state read back from '
                   "the model's (not in the paper; default 0)")
    p.add_argument('--anchor-equilibrium', action='store_true',
                   help='make x = 0, u = 3 an exact fixed point of the lifted model (not in the '
                   'paper)')
    p.add_argument('--data-seed', type=cli.SEED, default=0)
    p.add_argument('--test-trajectories', type=cli.integer(1), default=5000)
    p.add_argument('--test-seed', type=cli.SEED, default=datasets.TEST_SEED)
    p.add_argument('--epochs', type=cli.integer(1))
    p.add_argument('--lift-dim', type=int, help='K, the number of learned observables')
    p.add_argument('--hidden', type=cli.integer(1), help='Phi: units per hidden layer')
    p.add_argument('--layers', type=cli.integer(1), help='Phi: hidden layers')
    p.add_argument('--input-hidden', type=cli.integer(1), help='psi_ux: units per hidden layer')
    p.add_argument('--input-layers', type=cli.integer(1), help='psi_ux: hidden layers')
    p.add_argument('--batch-size', type=int)
    p.add_argument('--learning-rate', type=cli.number(above=0))
    p.add_argument('--seed', type=cli.SEED)
    p.add_argument('--device', type=cli.torch_device,
                   help='torch device (default: cuda if present, else cpu)')
    p.add_argument('--threads', type=cli.integer(1), help='torch CPU threads')
    p.add_argument('--resume', action='store_true', help='continue from <out>/checkpoint.pt')
    p.add_argument('--init', help='model directory to fine-tune (its config, with the flags '
                   'given)')
    p.add_argument('--structure', choices=tuple(kinds.KINDS),
                   help="lifted A: 'dense' (the paper's) or 'block' (observables stable by "
                   'construction; learning/block_koopman.py); default: the --init model\'s, '
                   'else dense')
    p.add_argument('--real-modes', type=int, default=12,
                   help='block, new model: real observable eigenvalues (the rest in pairs)')
    p.add_argument('--radius', type=float, default=1.0,
                   help='block: every observable eigenvalue inside |z| < radius')
    p.add_argument('--margin', type=float, default=0.995,
                   help='block, --init: observable eigenvalues beyond margin * radius are '
                   'pulled in to there')
    p.add_argument('--no-flat', action='store_true',
                   help='block: observables Phi(x) - Phi(0), not flat to first order at x = 0')
    p.add_argument('--observable-input', action='store_true',
                   help='block: the input enters the observables directly (B[n:] learned)')
    p.add_argument('--quiet', action='store_true')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        init, base, init_metadata = None, None, None
        if args.init:       # a directory or a shipped model's name, as retrain takes it
            init, model_config, init_metadata = model_file.load(shipped.resolve(args.init))
            base = model_file.KoopmanConfig.of(model_config, init_metadata)
        config = config_from_args(args, base)
        kind = kind_from_args(args, init_metadata)
        # --resume continues the run in --out, finished or not, also with more epochs
        # (docs/learning.md).
        model_file.check_free(args.out, args.overwrite or args.resume)
        if args.resume and not os.path.exists(os.path.join(args.out, CHECKPOINT)):
            # Said before the data is sampled (a minute), as Trainer.restore would after.
            raise ValueError(f'cannot resume: no {os.path.join(args.out, CHECKPOINT)}')
        train_data = load_data(args)
        test_data = data.test_set(args.test_trajectories, args.test_seed)
        trainer = Trainer(config, args.out, args.device, progress=not args.quiet, kind=kind)
        start = time.perf_counter()
        model = trainer.fit(train_data, resume=args.resume, init=init)
        seconds = time.perf_counter() - start
    except ValueError as error:
        print(f'train: {error}', file=sys.stderr)
        return 2
    except RuntimeError as error:     # torch: an init whose shapes the config does not fit
        print(f'train: cannot start from --init {args.init}: '
              f'{str(error).splitlines()[0]}', file=sys.stderr)
        return 2
    given = sys.argv[1:] if argv is None else argv
    command = 'python -m tsr_koopman_ctrl.commands.train ' + ' '.join(given)
    extra = {}
    if args.init:
        extra['init'] = args.init
    metadata = save_model(args.out, model, config, trainer, train_data, test_data, seconds,
                          command, extra, envelope=datasets.envelope(train_data))
    metrics = metadata['metrics']
    print(f"saved {args.out}: best epoch {trainer.best['epoch']}, test 30-step summed MSE "
          f"{metrics['test']['summed_mse']:.4g}, controllability rank "
          f"{metrics['controllability_rank']}/{config.model.lifted_dim}, {seconds:.0f} s")
    return 0


if __name__ == '__main__':
    sys.exit(main())
