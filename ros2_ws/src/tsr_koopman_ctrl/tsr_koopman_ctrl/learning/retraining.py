"""Retraining the deep Koopman model on recorded deployments, as a function.

    from tsr_koopman_ctrl.learning.retraining import retrain, RetrainOptions
    result = retrain(['bags/'], 'models/retrained', held_out=['bags_held_out/'],
                     options=RetrainOptions(init='koopman_default', epochs=10))
    result.errors_before, result.errors_after, result.provenance

Every bag is checked and cut into T-step windows (`learning.recorded`: the applied tension,
the bag's own units, no window across a gap). A bag without the simulator's RunInfo (hardware's,
another recorder's: only state and command) is read with the units, sample period and command
matching of the options (`sample_period`, `orbit_rate`, `tether_length`, `mass`,
`match_commands`; `bag.read_runs`). `init` fine-tunes that model (its weights and its
state normalisation; by default 10 epochs at a tenth of its learning rate); with
`from_scratch` only its config is used; without `init`, the default config (or `config`) from
scratch. `held_out` bags are whole bags never trained on: the 30-step prediction error on their
windows (mean, median, diverged fraction) is measured for the init model before training and
for the new one after, and so is the error on a fresh Table-1 test set (did the fine-tuning
forget the paper's range?). `sampled_ratio` R mixes R sampled Table-1 trajectories per recorded
window into the training data.

A bad bag is a ValueError naming it and what is wrong (every bad bag is named, not only the
first). Below a directory, the bag of a failed deployment (`bag.checks.mark_failed`) is skipped
with a warning line. With `skip_bad` bad training and held-out bags are skipped with a warning
line and recorded as skipped in the model's provenance; a bag given both to train and to hold
out is refused either way, also under another name or as a recovered copy (the same recorded
messages). Skipping that leaves nothing to test on (no usable held-out bag and no test
trajectories) is refused too. A crash-truncated bag is not bad: a warning says how much was
recovered, and its recovered windows are used.

The model file holds `save_model`'s metadata plus `retrain`: every bag with the sha256 of its
.mcap files and of its messages, and its message counts, the init model (path, weights sha256),
the errors before and after, the sampled mix, the command and the git commit.

Data-parallel (DistributedDataParallel, `learning.distributed`): with a context of W ranks,
rank r reads bags r, r + W, ... (with fewer bags than ranks every rank reads every bag and
takes windows r, r + W, ...); the batch size is the global batch, B / W windows per rank;
gradients are averaged by DDP; only rank 0 prints, evaluates the held-out bags and writes the
model.
"""

import dataclasses
import os
import subprocess
import sys
import time

import numpy as np

from tsr_koopman_ctrl.bag.checks import BagDataError, find_bags
from tsr_koopman_ctrl.bag.tsr_loop import reading_options
from tsr_koopman_ctrl.learning import dataset as datasets
from tsr_koopman_ctrl.learning import distributed, kinds, recorded
from tsr_koopman_ctrl.learning.deep_koopman import DeepKoopman
from tsr_koopman_ctrl.learning.trainer import evaluate, save_model, Trainer
from tsr_koopman_ctrl.model import model_file, shipped

FINE_TUNE_EPOCHS = 10
#: Overlapping training windows: on the loop's few bags a window every 3 steps lowered the
#: held-out error 3-4x where non-overlapping windows gave 1.5x (docs/data_loop.md).
DEFAULT_STRIDE = 3
#: Fewest in-zone steps for anchor 'data' to trust their mean command.
MIN_ANCHOR_SAMPLES = 100
#: Fine-tuning starts at this fraction of the init's learning rate: a model already fitted
#: should move, not restart.
FINE_TUNE_LEARNING_RATE_FACTOR = 0.1


class UsageError(ValueError):
    """A bad option or combination; one line."""


@dataclasses.dataclass(frozen=True)
class RetrainOptions:
    """How to retrain (module docstring); the command's options, one field each."""

    init: str = None                  # model to fine-tune: a directory or a shipped name
    from_scratch: bool = False        # with init: new weights with the init's config
    config: dict = dataclasses.field(default_factory=dict)   # KoopmanConfig fields to change
    sampled_ratio: float = 0.0        # sampled Table-1 trajectories per recorded window
    data_seed: int = 0                # seed of the sampled mix
    test_trajectories: int = 2000     # Table-1 test trajectories for the error (0: none)
    steps: int = recorded.DEFAULT_STEPS
    stride: int = DEFAULT_STRIDE      # a training window every `stride` steps
    anchor: object = 'data'           # 'data', 'init' or a tension
    epochs: int = None                # fine-tuning: FINE_TUNE_EPOCHS; else the config's
    learning_rate: float = None       # fine-tuning: a tenth of the init's
    batch_size: int = None            # global batch (split over the ranks)
    seed: int = None                  # training seed
    namespace: str = None             # the loop to read in bags holding several
    skip_bad: bool = False            # skip bad bags with a warning
    device: str = None                # torch device (default: cuda if present, else cpu)
    progress: bool = True             # per-epoch lines and progress bars
    overwrite: bool = False           # replace a model already in `out`
    # How to read a bag without the simulator's RunInfo (hardware's): `bag.read_runs`.
    sample_period: float = None       # [s] (default: from the states' stamps)
    orbit_rate: float = None          # [rad/s] the units (default: the paper's)
    tether_length: float = None       # [m]
    mass: float = None                # [kg]
    match_commands: str = None        # 'step' or 'time' (default: from the simulator's mode)


@dataclasses.dataclass
class RetrainResult:
    """A retrained model: where it is, its scores before and after, its provenance."""

    model: str
    errors_before: dict               # {'held_out' / 'table1': error summary or None}
    errors_after: dict
    best_epoch: int                   # 0: no epoch beat the init's weights
    seconds: float
    anchor_tension: float
    provenance: dict                  # the model file's `retrain` record


def checked_overrides(values):
    """KoopmanConfig fields to change, checked: an unknown name is one line."""
    if not isinstance(values, dict):
        raise UsageError('--config-json: not a JSON object')
    # Named here, before any other check could read an unknown key as a changed one; a
    # retired option at its "off" value means nothing, as in a model file.
    values, unknown = model_file.KoopmanConfig.current_options(values)
    if unknown:
        known = sorted(model_file.KoopmanConfig.names())
        raise UsageError(f'--config-json: unknown field{"s" if len(unknown) > 1 else ""} '
                         f'{", ".join(unknown)} (known: {", ".join(known)})')
    return values


def configure(options, out):
    """(config, init record or None, init tensors or None, init model config, model kind,
    init envelope or None): the model to train and where from. A fine-tuned model keeps its
    kind (`kinds.from_metadata`), its ModelConfig (what the network is and computes) but for
    the anchor, which `anchored` sets (retrain's --anchor), and the envelope it was trained in;
    from scratch it is dense."""
    args = options
    init, tensors, base, model_kind = None, None, model_file.KoopmanConfig(), kinds.Dense()
    envelope = None
    if args.from_scratch and not args.init:
        raise UsageError('--from-scratch needs --init (without --init training is from scratch)')
    if args.init:
        path = shipped.resolve(args.init)
        tensors, model_config, metadata = model_file.load(path)
        base = model_file.KoopmanConfig.of(model_config, metadata)
        if not args.from_scratch:
            try:
                model_kind = kinds.from_metadata(metadata)
            except ValueError as error:
                raise UsageError(f'--init {args.init}: {error}')
            envelope = metadata.get('envelope')
        init = {'given': args.init, 'path': os.path.abspath(path),
                'weights_sha256': model_file.weights_sha256(path),
                'fine_tuned': not args.from_scratch}
        if os.path.realpath(out) == os.path.realpath(path):
            raise UsageError(f'--out {out} is the init model: write the new one elsewhere')
    fine_tune = init is not None and not args.from_scratch
    values = base.as_dict()
    overrides = checked_overrides(dict(args.config))
    if fine_tune:
        model_fields = dataclasses.asdict(base.model)
        fixed = sorted(k for k in overrides if k in model_fields and overrides[k] != (
            list(model_fields[k]) if isinstance(model_fields[k], tuple) else model_fields[k]))
        if fixed:
            instead = ('--anchor' if fixed == ['anchor_tension'] else '--from-scratch')
            raise UsageError(f'cannot fine-tune with another {", ".join(fixed)} than the init '
                             f'model: use {instead}')
        values['epochs'] = FINE_TUNE_EPOCHS
        values['learning_rate'] = (base.training.learning_rate
                                   * FINE_TUNE_LEARNING_RATE_FACTOR)
    values.update(overrides)
    for key, value in (('epochs', args.epochs), ('learning_rate', args.learning_rate),
                       ('batch_size', args.batch_size), ('seed', args.seed)):
        if value is not None:
            values[key] = value
    values['final_learning_rate'] = min(values['final_learning_rate'], values['learning_rate'])
    try:
        config = model_file.KoopmanConfig.from_dict(values)
    except (TypeError, ValueError) as error:
        raise UsageError(f'bad config: {error}')
    return config, init, tensors, base.model, model_kind, envelope


def loop_reading(args):
    """How `read_windows` reads a bag without the simulator's RunInfo, from the options
    (UsageError, one line, for a bad one)."""
    try:
        return reading_options(args.sample_period, args.orbit_rate, args.tether_length,
                               args.mass, args.match_commands)
    except ValueError as error:
        raise UsageError(str(error))


def parse_anchor(text):
    """'data', 'init' or a tension (float); UsageError otherwise."""
    if text in ('data', 'init'):
        return text
    try:
        return float(text)
    except ValueError:
        raise UsageError(f"--anchor must be 'data', 'init' or a number, got {text!r}")


def anchored(config, anchor, zone_commands):
    """(config with its anchor tension, a record of where it came from). 'data': the mean
    command over the training bags' steps inside the 1% zone (where the plant holds the deployed
    equilibrium; `zone_commands` are the bags' {'steps', 'sum'}, each step counted once); kept
    as it is with fewer than MIN_ANCHOR_SAMPLES such steps."""
    if anchor == 'init':
        return config, {'source': 'init', 'tension': config.model.anchor_tension}
    if anchor != 'data':
        return with_anchor(config, anchor), {'source': 'given', 'tension': anchor}
    count = sum(int(z['steps']) for z in zone_commands)
    total = sum(float(z['sum']) for z in zone_commands)
    if count < MIN_ANCHOR_SAMPLES:
        return config, {'source': f'init (only {count} in-zone steps to estimate from)',
                        'tension': config.model.anchor_tension, 'samples': count}
    tension = total / count
    return with_anchor(config, tension), {'source': f'data ({count} in-zone steps)',
                                          'tension': tension, 'samples': count}


def with_anchor(config, tension):
    try:
        return config.replace(anchor_tension=float(tension))
    except ValueError as error:
        raise UsageError(f'bad --anchor: {error}')


# --------------------------------------------------------------------------- data

def _read(paths, options, indices):
    """read_windows for the bags at `indices`: {index: BagWindows or the error's line}. Each
    bag's index offsets its validation blocks (`recorded.validation_blocks`)."""
    results = {}
    for index in indices:
        try:
            offset = {'validation_offset': index} if options.get('validation_fraction') else {}
            results[index] = recorded.read_windows(paths[index], **options, **offset)
        except BagDataError as error:
            results[index] = str(error)
    return results


def agree(error):
    """Raise on every rank if any rank failed (the lowest rank's error), so that no rank is
    left waiting in a collective for one that stopped."""
    errors = [e for e in distributed.gather(error) if e]
    if errors:
        raise UsageError(errors[0])


def _summary(result):
    """What rank 0 needs to know about a bag another rank read (no arrays)."""
    if isinstance(result, str):
        return result
    return {'provenance': result.provenance, 'warnings': result.warnings}


def _identity(summary):
    """What makes two bags the same data: their recorded messages, not their files' bytes (a
    `bag recover` or re-chunked copy has other files)."""
    return summary['provenance']['messages_sha256']


def _check(train_paths, held_paths, train, held, skip_bad):
    """Lines for bad and duplicated bags; the indices of the usable ones. Raises for a bag
    held out and trained on (never skipped: the comparison would be meaningless)."""
    held_hashes = {_identity(s): held_paths[i] for i, s in held.items()
                   if not isinstance(s, str)}
    for index, s in train.items():
        if not isinstance(s, str) and _identity(s) in held_hashes:
            raise UsageError(f"{train_paths[index]} has the same content as the held-out bag "
                             f"{held_hashes[_identity(s)]}: a bag is trained on or held out, "
                             'not both')
    bad, seen = [], {}
    for kind, paths, results in (('training', train_paths, train),
                                 ('held-out', held_paths, held)):
        for index in sorted(results):
            s = results[index]
            if isinstance(s, str):
                bad.append((kind, index, s))
                continue
            digest = _identity(s)
            # Training bags were checked against held-out ones above, so a repeat here is a
            # bag given twice as training or twice as held-out (counted twice in the scores).
            if digest in seen:
                bad.append((kind, index, f'{paths[index]}: same messages (sha256 {digest[:12]}) '
                            f'as {seen[digest]}, given twice'))
            seen.setdefault(digest, paths[index])
    if bad and not skip_bad:
        raise UsageError('\n'.join(f'retrain: {line}' for _, _, line in bad)
                         + f'\nretrain: {len(bad)} bad bags (--skip-bad skips them)')
    return bad


def errors_summary(metrics):
    return {k: metrics[k] for k in ('summed_mse', 'summed_mse_median', 'diverged_fraction',
                                    'windows')}


def error_line(name, metrics):
    if metrics is None:
        return f'  {name}: -'
    return (f"  {name}: mean {metrics['summed_mse']:.4g}, median "
            f"{metrics['summed_mse_median']:.4g}, diverged {metrics['diverged_fraction']:.1%}")


def git_commit():
    try:
        done = subprocess.run(['git', 'rev-parse', 'HEAD'], capture_output=True, text=True,
                              cwd=os.path.dirname(os.path.realpath(__file__)), timeout=10)
    except (OSError, subprocess.SubprocessError):
        return 'unknown'
    return done.stdout.strip() if done.returncode == 0 and done.stdout.strip() else 'unknown'


class DataSummary:
    """What save_model records about the training data of every rank."""

    def __init__(self, provenance, count):
        self.provenance, self.count = provenance, count

    def __len__(self):
        return self.count


# --------------------------------------------------------------------------- retraining

@dataclasses.dataclass
class BagSet:
    """The training and held-out bags as every rank sees them: their paths, what this rank read
    (`local`, `local_held`: BagWindows or the error's line), what every rank read (`train`,
    `held`: provenance and warnings or the error's line), the bad ones and what is used."""

    train_paths: list
    held_paths: list
    local: dict
    local_held: dict
    train: dict
    held: dict
    bad: list
    by_bags: bool       # ranks share out bags (else every rank reads every bag: windows)

    @property
    def skipped(self):
        return {(kind, index) for kind, index, _ in self.bad}

    @property
    def used(self):
        """Indices of the training bags trained on."""
        return [i for i in sorted(self.train) if ('training', i) not in self.skipped]

    def usable_held(self):
        return [i for i in sorted(self.held)
                if not isinstance(self.held[i], str) and ('held-out', i) not in self.skipped]


def read_bag_set(bags, held_out, args, config, context, say):
    """Find and read the bags (each rank its shard, rank 0 the held-out ones too), gather what
    every rank found so that all take the same decisions (stop, skip), and say what is used."""
    skipped = []                       # the bags of failed deployments below a directory
    train_paths = find_bags(bags, skipped)
    held_paths = find_bags(held_out, skipped) if held_out else []
    for line in skipped:
        say(f'retrain: warning: {line}', file=sys.stderr)
    held_real = {os.path.realpath(p) for p in held_paths}
    both = [p for p in train_paths if os.path.realpath(p) in held_real]
    if both:
        raise UsageError(f'{", ".join(both)}: given to train on and held out; a bag is one or '
                         'the other')
    held_options = {'steps': args.steps, 'namespace': args.namespace, 'h': config.model.h,
                    'state_dim': config.model.state_dim, **loop_reading(args)}
    options = dict(held_options, stride=args.stride,
                   validation_fraction=config.training.validation_fraction)
    by_bags = len(train_paths) >= context.world_size
    mine = (distributed.shard(list(range(len(train_paths))), context) if by_bags
            else list(range(len(train_paths))))
    local, local_held, failed = {}, {}, None
    try:
        local = _read(train_paths, options, mine)
        if context.is_main:
            local_held = _read(held_paths, held_options, range(len(held_paths)))
    except ValueError as error:        # not a bag's fault (the installed definitions)
        failed = str(error)
    agree(failed)
    gathered = distributed.gather(({i: _summary(r) for i, r in local.items()},
                                   {i: _summary(r) for i, r in local_held.items()}))
    train, held = {}, {}
    for part_train, part_held in gathered:
        train.update(part_train)
        held.update(part_held)
    bad = _check(train_paths, held_paths, train, held, args.skip_bad)
    found = BagSet(train_paths, held_paths, local, local_held, train, held, bad, by_bags)
    for index in found.used:
        for warning in train[index]['warnings']:
            say(f'retrain: warning: {warning}', file=sys.stderr)
        say(f"{train_paths[index]}: {train[index]['provenance']['windows']} windows",
            flush=True)
    for kind, index, line in bad:
        say(f'retrain: warning: skipped {kind} bag: {line}', file=sys.stderr)
    if not found.used:
        raise UsageError('no usable training bag')
    # --skip-bad may leave nothing to score the models on; the model file needs a test error,
    # so this is refused before training, as giving nothing to test on is.
    if held_out and not args.test_trajectories and not found.usable_held():
        raise UsageError('no usable held-out bag and --test-trajectories 0: nothing to test on '
                         '(give a usable --held-out bag or --test-trajectories > 0)')
    return found


def training_windows(found, context):
    """This rank's training windows and validation windows (or None: the trainer's random
    split, on every rank alike)."""
    mine_used = [i for i in sorted(found.local) if ('training', i) not in found.skipped]
    parts = [found.local[i].data for i in mine_used]
    data = datasets.concatenate(parts) if parts else None
    held_parts = [found.local[i].validation for i in mine_used
                  if found.local[i].validation is not None]
    validation = datasets.concatenate(held_parts) if held_parts else None
    if data is not None and not found.by_bags:
        data = data.subset(np.arange(context.rank, len(data), context.world_size))
        if validation is not None:
            validation = validation.subset(
                np.arange(context.rank, len(validation), context.world_size))
    # Validation blocks on every rank, or the trainer's random split on every rank (bags too
    # short for a block of three windows).
    if not all(distributed.gather(validation is not None and len(validation) > 0)):
        validation = None
    agree(None if data is not None and len(data) else
          f'rank {context.rank} has no usable bag (bags are shared out one by one over the '
          'ranks: use fewer ranks)')
    return data, validation


def test_sets(found, held_out, args, config, say):
    """{'held_out': the usable held-out bags' windows, 'table1': a fresh sampled test set}, as
    asked for (rank 0)."""
    tests = {}
    parts = [found.local_held[i].data for i in found.usable_held() if i in found.local_held]
    if parts:
        tests['held_out'] = datasets.concatenate(parts)
    elif held_out:
        say('retrain: warning: no usable held-out bag', file=sys.stderr)
    else:
        say('retrain: warning: no --held-out bags: no error on recorded data the model never '
            'saw', file=sys.stderr)
    if args.test_trajectories:
        tests['table1'], _ = datasets.sample(datasets.SamplingConfig(
            trajectories=args.test_trajectories, steps=args.steps, h=config.model.h,
            seed=datasets.TEST_SEED))
    return tests


def retrain(bags, out, held_out=(), options=None, context=None, command=None):
    """Retrain on recorded bags (module docstring): the RetrainResult on the main rank, None
    on the others. `options`: RetrainOptions; `context`: a `distributed` context (default: one
    process); `command`: what the model file records as the command that made it. Progress goes
    to stdout, warnings to stderr; a bad bag, option or model is a ValueError (one line, or one
    line per bad bag)."""
    args = options or RetrainOptions()
    context = context or distributed.Context()
    say = print if context.is_main else (lambda *a, **k: None)
    if args.steps < 1 or args.stride < 1 or args.sampled_ratio < 0 or args.test_trajectories < 0:
        raise UsageError('--steps and --stride must be >= 1, --sampled-ratio and '
                         '--test-trajectories >= 0')
    model_file.check_free(out, args.overwrite)
    anchor = parse_anchor(args.anchor)
    loop_reading(args)                  # checked before any work; read_bag_set applies it
    config, init, init_tensors, init_config, model_kind, init_envelope = configure(
        args, out)
    if anchor not in ('data', 'init'):
        with_anchor(config, anchor)     # checked before the bags are read; anchored() applies it
    fine_tune = init is not None and init['fine_tuned']
    if config.training.batch_size % context.world_size:
        raise UsageError(f'--batch-size {config.training.batch_size} does not split evenly over '
                         f'{context.world_size} ranks')
    if not held_out and not args.test_trajectories:
        raise UsageError('nothing to test on: give --held-out bags or --test-trajectories > 0')

    found = read_bag_set(bags, held_out, args, config, context, say)
    data, validation = training_windows(found, context)
    recorded_windows = len(data)
    config, anchor_record = anchored(
        config, anchor, [found.train[i]['provenance']['zone_commands'] for i in found.used])
    say(f"anchor tension {config.model.anchor_tension:.4f} ({anchor_record['source']})",
        flush=True)
    sampled = None
    if args.sampled_ratio > 0:
        count = int(round(args.sampled_ratio * len(data)))
        if count:
            sampled, _ = datasets.sample(datasets.SamplingConfig(
                trajectories=count, steps=args.steps, h=config.model.h,
                seed=args.data_seed + context.rank))
            data = datasets.concatenate([data, sampled])
    total_validation = sum(distributed.gather(len(validation) if validation is not None else 0))
    counts = distributed.gather((recorded_windows, sampled.provenance if sampled else []))
    total_recorded = sum(n for n, _ in counts)
    sampled_provenance = [dict(p, ratio=args.sampled_ratio) for _, ps in counts for p in ps]
    total_sampled = sum(p['kept'] for p in sampled_provenance)
    say(f'training on {total_recorded} recorded windows from {len(found.used)} bags'
        + (f' and {total_sampled} sampled Table-1 trajectories (ratio {args.sampled_ratio:g})'
           if sampled_provenance else '')
        + (f', {context.world_size} ranks sharing out '
           f'{"bags" if found.by_bags else "windows"}' if context.active else ''), flush=True)

    # The supervisor's envelope: the states of every rank's training data and, fine-tuned, the
    # states the init was trained on (it still predicts there).
    envelope = datasets.widest(init_envelope if fine_tune else None,
                               *distributed.gather(datasets.envelope(data) if len(data) else None))
    trainer = Trainer(config, device=args.device, progress=args.progress,
                      kind=model_kind)
    tests, before = {}, {}
    if context.is_main:
        tests = test_sets(found, held_out, args, config, say)
        before = {name: None for name in tests}
        if init is not None:
            net = DeepKoopman.from_numpy(init_tensors, init_config).to(trainer.device).eval()
            before = {name: errors_summary(evaluate(net, d, trainer.device))
                      for name, d in tests.items()}
        for name, d in tests.items():
            say(f'{name} {args.steps}-step summed MSE before ({len(d)} windows):')
            say(error_line(f'init {args.init}', before[name]) if init else '  (no init model)',
                flush=True)

    began = time.perf_counter()
    say(f'validation (the best epoch): {total_validation} windows set aside from the training '
        'bags, sharing no step with a training window' if total_validation else
        'validation (the best epoch): a random split of the training windows (no bag had a '
        'validation block)', flush=True)
    model = trainer.fit(data, init=init_tensors if fine_tune else None, validation=validation)
    seconds = time.perf_counter() - began
    if not context.is_main:
        return None

    after = {name: errors_summary(evaluate(model, d, trainer.device))
             for name, d in tests.items()}
    command = command or f'tsr_koopman_ctrl.learning.retrain({list(bags)!r}, {out!r}, ...)'
    bag_provenance = [found.train[i]['provenance'] for i in found.used]
    record = {
        'bags': [{k: p[k] for k in ('path', 'sha256', 'messages_sha256', 'files', 'messages',
                                    'windows')}
                 for p in bag_provenance],
        'held_out': [found.held[i]['provenance'] for i in found.usable_held()],
        'skipped': [{'kind': kind,
                     'bag': (found.train_paths if kind == 'training' else found.held_paths)[i],
                     'error': line} for kind, i, line in found.bad],
        'init': init, 'steps': args.steps, 'stride': args.stride, 'anchor': anchor_record,
        'validation_windows': total_validation,
        'recorded_windows': total_recorded,
        'sampled_ratio': args.sampled_ratio, 'sampled_trajectories': total_sampled,
        'errors_before': before, 'errors_after': after,
        'world_size': context.world_size, 'sharding': 'bags' if found.by_bags else 'windows',
        'per_rank_batch': config.training.batch_size // context.world_size,
        'git_commit': git_commit(), 'command': command}
    summary = DataSummary(bag_provenance + sampled_provenance,
                          total_recorded + total_sampled)
    test_data = tests.get('held_out', tests.get('table1'))
    save_model(out, model, config, trainer, summary, test_data, seconds, command,
               extra={'retrain': record}, envelope=envelope)
    return RetrainResult(model=str(out), errors_before=before, errors_after=after,
                         best_epoch=trainer.best['epoch'], seconds=seconds,
                         anchor_tension=config.model.anchor_tension, provenance=record)
