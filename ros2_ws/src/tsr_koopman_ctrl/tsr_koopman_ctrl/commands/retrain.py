"""Retrain the deep Koopman model on recorded deployments: ``retrain --bags BAG_OR_DIR ...
--out models/NAME [--init MODEL] [--held-out BAG_OR_DIR ...]``.

A bag needs only tsr/state and tsr/tension_cmd: one without the simulator's RunInfo (hardware's)
is read with --orbit-rate, --tether-length, --mass, --sample-period and --match-commands.
Parses the options and calls `learning.retraining.retrain`, whose docstring says what is done;
prints the errors before and after and where the model went. A bad bag or option is one line
(one per bad bag) and exit status 2.

Data-parallel: the same command under ``torchrun --nproc_per_node=W -m
tsr_koopman_ctrl.commands.retrain ...`` (DistributedDataParallel; only rank 0 prints and
writes; a bad option is rank 0's one line, then torchrun's own report).
"""

import argparse
import json
import os
import pathlib
import shlex
import sys

from tsr_koopman_ctrl.commands import cli
from tsr_koopman_ctrl.learning import distributed, recorded
from tsr_koopman_ctrl.learning.retraining import (DEFAULT_STRIDE, error_line,
                                                  FINE_TUNE_EPOCHS, retrain, RetrainOptions,
                                                  UsageError)


class _Quiet(argparse.ArgumentParser):
    """Only rank 0 prints an option error (every rank still exits 2)."""

    def error(self, message):
        if distributed.launched().is_main:
            self.print_usage(sys.stderr)
            print(f'{self.prog}: error: {message}', file=sys.stderr)
        sys.exit(2)


def parser():
    p = _Quiet(prog='retrain', description=__doc__.split('\n\n')[0])
    p.add_argument('--bags', nargs='+', action='extend', required=True, metavar='BAG_OR_DIR',
                   help='bags to train on (a directory: every bag below it)')
    p.add_argument('--out', required=True, type=cli.model_dir, help='model directory to write')
    cli.add_overwrite(p)
    p.add_argument('--init', metavar='MODEL',
                   help='model to fine-tune (a directory or a shipped name)')
    p.add_argument('--from-scratch', action='store_true',
                   help="with --init: train new weights with the init's config")
    p.add_argument('--config-json', metavar='JSON_OR_FILE',
                   help='config overrides (KoopmanConfig fields) as JSON text or a file; '
                   'with fine-tuning only training settings')
    p.add_argument('--held-out', nargs='+', action='extend', default=[], metavar='BAG_OR_DIR',
                   help='bags never trained on, for the error before and after')
    p.add_argument('--sampled-ratio', type=cli.number(0), default=0.0, metavar='R',
                   help='sampled Table-1 trajectories per recorded window to mix in (0)')
    p.add_argument('--data-seed', type=int, default=0, help='seed of the sampled mix')
    p.add_argument('--test-trajectories', type=int, default=2000,
                   help='Table-1 test trajectories for the error before and after (0: none)')
    p.add_argument('--steps', type=int, default=recorded.DEFAULT_STEPS,
                   help='steps per window (30)')
    p.add_argument('--stride', type=int, default=DEFAULT_STRIDE,
                   help=f'a training window starts every STRIDE steps ({DEFAULT_STRIDE}: '
                   'overlapping; held-out windows never overlap)')
    p.add_argument('--anchor', default='data', metavar='data|init|TENSION',
                   help="equilibrium tension the model is anchored at: 'data' (the mean "
                   "command over the training bags' steps inside the 1%% zone), 'init' (the "
                   "init model's or config's), or a number")
    p.add_argument('--epochs', type=cli.integer(1),
                   help=f'epochs (fine-tuning: {FINE_TUNE_EPOCHS}; else the config\'s)')
    p.add_argument('--learning-rate', type=cli.number(above=0),
                   help='initial learning rate (fine-tuning: a tenth of the init\'s)')
    p.add_argument('--batch-size', type=int, help='global batch (split over the ranks)')
    p.add_argument('--seed', type=cli.SEED, help='training seed')
    p.add_argument('--namespace', help='the loop to read in bags holding several')
    p.add_argument('--skip-bad', action='store_true',
                   help='skip bad bags with a warning instead of exit 2')
    p.add_argument('--device', type=cli.torch_device,
                   help='torch device (default: cuda if present, else cpu)')
    p.add_argument('--threads', type=cli.integer(1), help='torch CPU threads (per rank)')
    p.add_argument('--quiet', action='store_true', help='no per-epoch lines or progress bars')
    cli.add_loop_reading(p)
    return p


def config_overrides(text):
    """--config-json: JSON text or a file holding it -> {field: value} (UsageError, one line)."""
    if not text:
        return {}
    try:
        # A file if there is one; else JSON text ('[1]' is then refused, not a path).
        source = pathlib.Path(text).read_text() if os.path.isfile(text) else text
        if source is text and text.lstrip()[:1] not in '{[':
            raise ValueError(f'{text}: neither a file nor a JSON object')
        return json.loads(source)
    except (OSError, ValueError) as error:
        raise UsageError(f'--config-json: {error}')


def options(args):
    return RetrainOptions(
        init=args.init, from_scratch=args.from_scratch, config=config_overrides(args.config_json),
        sampled_ratio=args.sampled_ratio, data_seed=args.data_seed,
        test_trajectories=args.test_trajectories, steps=args.steps, stride=args.stride,
        anchor=args.anchor, epochs=args.epochs, learning_rate=args.learning_rate,
        batch_size=args.batch_size, seed=args.seed, namespace=args.namespace,
        skip_bad=args.skip_bad, device=args.device, progress=not args.quiet,
        overwrite=args.overwrite, sample_period=args.sample_period, orbit_rate=args.orbit_rate,
        tether_length=args.tether_length, mass=args.mass, match_commands=args.match_commands)


def main(argv=None):
    args = parser().parse_args(argv)
    if args.threads:
        import torch
        torch.set_num_threads(args.threads)
    context = distributed.start('gloo' if args.device == 'cpu' else None)
    given = sys.argv[1:] if argv is None else list(argv)
    command = 'retrain ' + ' '.join(shlex.quote(a) for a in given)
    try:
        result = retrain(args.bags, args.out, args.held_out, options(args), context, command)
    except ValueError as error:        # BagDataError, UsageError, ModelFileError, the trainer's
        if context.is_main:
            text = str(error)
            print(text if text.startswith('retrain: ') else f'retrain: {text}',
                  file=sys.stderr)
        return 2
    finally:
        distributed.stop()
    if result is None:                 # not the main rank
        return 0
    for name, before in result.errors_before.items():
        print(f'{name} {args.steps}-step summed MSE, before -> after:')
        print(error_line(f'init {args.init}' if args.init else 'init (none)', before))
        print(error_line(f'new  {args.out}', result.errors_after[name]))
    kept = (" (no epoch lowered the validation error: the init's weights, anchored at "
            f"u = {result.anchor_tension:.4g})" if result.best_epoch == 0 else '')
    print(f'saved {args.out}: best epoch {result.best_epoch}{kept}, {result.seconds:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
