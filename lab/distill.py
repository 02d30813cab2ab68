"""A smaller model for koopman_nmpc's planner, distilled from the shipped one, and its cost.

    python -m lab.distill train (--init DIR | --fresh 64 2 32 2) --out DIR [--targets teacher]
    python -m lab.distill compare --model koopman_retrieval --model models/koopman_planner \\
        [--out out/distill]

`train` fits a model (normally a student `commands.train` trained with a small config,
`--init`) on the planner's objective alone: the relifted map x+ = C (A psi_x(x) + B psi_u(x,
u)), not the lifted linear roll:

(a) one step from fresh samples every batch (`one_step_samples`: states uniform in the
    teacher's three boxes in its data's proportions, Table 1, the equilibrium box and
    retrieval; tensions uniform or, one in three, at 0 or 5), the next state the plant's
    (`--targets plant`, RK4 with the data's 10 substeps) or the teacher's relifted step
    (`--targets teacher`); the error per component relative to the plant's increment plus a
    floor (`--floor` x the median |increment|), so the stiff short tether, whose increments
    are 1e4 x larger, does not swamp the states the controller regulates;
(b) the relifted map iterated over the 30-step windows of the teacher's training data from
    x_0 (state error over the model's normalisation, discounted by gamma as L_rec),
    weighted by --weight-rollout.

Adam, cosine learning rate, gradient norm clipped to 1; the best epoch by the same loss on
held-out samples (plant targets) and validation windows is saved with `trainer.save_model`: an
ordinary model directory (its recorded test error is the lifted linear roll's, which this
objective does not train).

`compare` measures each model against the plant, one run, the models side by side:

- prediction, on held-out sampled sets (seeds no training run uses): the 30-step state MSE
  summed over the steps of the lifted linear roll (the figure model.json records) and of the
  relifted map (what the planner iterates), and the one-step MSE of the relifted map from
  every state of the sets (`learning.errors.multistep_errors`, averaged over components);
- closed loop: koopman_nmpc on the model, offset-free as deployed, from the comparison and
  held-out starts (the figures of `evaluation.closed_loop_figures`): settle time, frontier
  ratio, overshoot, fallbacks; and the model's one-step MSE along those deployments (every
  visited state under the tension flown there, against the plant's step).

Writes compare.json and compare.md under --out and prints the tables.
"""

import argparse
import json
import pathlib
import sys
import time

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl import arguments
from tsr_koopman_ctrl.learning import dataset as datasets
from tsr_koopman_ctrl.learning import errors

#: Held-out sets: (name, box low, box high, trajectories, seed); the Table-1 one is the test
#: set every model.json records (TEST_SEED), the others seeds no training run uses.
HELD_OUT = (
    ('table1', None, None, 5000, datasets.TEST_SEED),
    ('equilibrium', datasets.EQUILIBRIUM_BOX_LOW, datasets.EQUILIBRIUM_BOX_HIGH, 2000,
     datasets.TEST_SEED + 1),
    ('retrieval', datasets.RETRIEVAL_BOX_LOW, datasets.RETRIEVAL_BOX_HIGH, 2000,
     datasets.TEST_SEED + 2))


def held_out_sets():
    sets = {}
    for name, low, high, trajectories, seed in HELD_OUT:
        box = {} if low is None else {'state_low': tuple(map(float, low)),
                                      'state_high': tuple(map(float, high))}
        sets[name] = datasets.sample(datasets.SamplingConfig(
            trajectories=trajectories, seed=seed, **box))[0]
    return sets


def prediction_errors(model, data):
    """{'linear', 'relifted': 30-step summed MSE, 'one_step': relifted one-step MSE} on
    `data` (against the plant's states)."""
    x0, u = data.x[:, 0], data.u
    linear = errors.multistep_errors(model.predict(x0, u), data.x)
    relifted = errors.multistep_errors(model.predict(x0, u, relift=True), data.x)
    states, following = data.x[:, :-1].reshape(-1, model.n), data.x[:, 1:].reshape(-1, model.n)
    one_step = float(np.mean((model.step(states, data.u.reshape(-1)) - following) ** 2))
    return {'linear': linear['summed_mse'], 'relifted': relifted['summed_mse'],
            'relifted_diverged': relifted['diverged_fraction'], 'one_step': one_step}


def closed_loop_rows(model, starts, steps):
    """koopman_nmpc on `model` from each start (`evaluation.closed_loop_figures`'s figures),
    and the model's one-step MSE against the plant along those deployments."""
    from tsr_koopman_ctrl.control import closed_loop, make_controller
    from tsr_koopman_ctrl.evaluation import run_figures
    from tsr_koopman_ctrl.model.lifted import LiftedModel
    lifted, rows, squared = LiftedModel.load(model), [], []
    for start in starts:
        law = make_controller('koopman_nmpc', model=model)
        states, tensions = closed_loop(law, start, steps)
        figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions,
                              start=start, halted=len(states) <= steps)
        # the plant's one step from every visited state under the tension flown there
        following = dynamics.rollout(states[:-1], np.asarray(tensions)[:, None],
                                     dynamics.PAPER_STEP, 10)[:, 1]
        squared.append((lifted.step(states[:-1], tensions) - following) ** 2)
        rows.append({'start': list(start), 'fallbacks': law.fallbacks, **{k: figures[k] for k in (
            'settle_tau', 'frontier_ratio', 'length_overshoot', 'swing')}})
    return rows, float(np.concatenate(squared).mean())


def compare(models, steps, log=print):
    from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, HELD_OUT_STARTS
    from tsr_koopman_ctrl.model.lifted import LiftedModel
    sets = held_out_sets()
    results = {}
    for name in models:
        model = LiftedModel.load(name)
        config = model.config
        results[name] = {
            'architecture': f'Phi {config.layers} x {config.hidden}, psi_ux '
                            f'{config.input_layers} x {config.input_hidden}, K {config.lift_dim}',
            'prediction': {key: prediction_errors(model, data) for key, data in sets.items()}}
        log(f'{name}: prediction {json.dumps(results[name]["prediction"])}')
        begin = time.perf_counter()
        rows, along = closed_loop_rows(name, COMPARISON_STARTS + HELD_OUT_STARTS, steps)
        results[name]['closed_loop'] = rows
        results[name]['prediction']['own_closed_loop'] = {'one_step': along}
        log(f'{name}: closed loop in {time.perf_counter() - begin:.0f} s')
    return results


def markdown(results):
    names = list(results)
    lines = ['| metric | ' + ' | '.join(names) + ' |', '|---' * (len(names) + 1) + '|',
             '| networks | ' + ' | '.join(results[n]['architecture'] for n in names) + ' |']
    sets = list(next(iter(results.values()))['prediction'])
    for key, label in (('linear', '30-step summed MSE, lifted linear roll'),
                       ('relifted', '30-step summed MSE, relifted map'),
                       ('one_step', 'one-step MSE, relifted map')):
        for data in sets:
            if key not in results[names[0]]['prediction'][data]:
                continue
            lines.append(f'| {label}, {data} | ' + ' | '.join(
                f"{results[n]['prediction'][data][key]:.4g}" for n in names) + ' |')
    lines += ['', '| start | ' + ' | '.join(f'{n} settle tau (ratio)' for n in names)
              + ''.join(f' | {n} settle change' for n in names[1:]) + ' |',
              '|---' * (2 * len(names)) + '|']

    def cell(row):
        if row['settle_tau'] is None:
            return 'not settled'
        ratio = '-' if row['frontier_ratio'] is None else f"{row['frontier_ratio']:.3f}"
        return f"{row['settle_tau']:.2f} ({ratio}) ov {row['length_overshoot']:.3f}" + (
            f" fb {row['fallbacks']}" if row['fallbacks'] else '')

    def change(row, reference):
        if row['settle_tau'] is None or reference['settle_tau'] is None:
            return '-'
        return f"{100.0 * (row['settle_tau'] / reference['settle_tau'] - 1.0):+.1f}%"
    for i, first in enumerate(results[names[0]]['closed_loop']):
        rows = [results[n]['closed_loop'][i] for n in names]
        lines.append(f"| {tuple(first['start'])} | " + ' | '.join(cell(r) for r in rows)
                     + ''.join(f' | {change(r, first)}' for r in rows[1:]) + ' |')
    return '\n'.join(lines) + '\n'


def relifted_step(model, x, u):
    """The torch model's relifted one-step map, x+ = C (A psi_x(x) + B psi_u(x, u)), in the
    model's state s and mapped back to the physical state."""
    n = model.config.state_dim
    z = model.psi_x(x)
    following = z @ model.A[:n].T + model.psi_u(z[..., :n], u).unsqueeze(-1) * model.B[:n].T
    return model.physical_state(following)


#: Boxes the fresh one-step samples come from, with their shares: the teacher's data in its
#: proportions (39 545 Table-1, 10 000 equilibrium, 13 517 retrieval trajectories).
BOXES = ((dynamics.TABLE1_STATE_LOW, dynamics.TABLE1_STATE_HIGH, 0.63),
         (datasets.EQUILIBRIUM_BOX_LOW, datasets.EQUILIBRIUM_BOX_HIGH, 0.16),
         (datasets.RETRIEVAL_BOX_LOW, datasets.RETRIEVAL_BOX_HIGH, 0.21))


def one_step_samples(rng, size, teacher=None):
    """(x, u, x+): states uniform in the boxes, tensions uniform in [0, 5] or (one in three)
    at 0 or 5 (how the NMPC flies), x+ the plant's (the data's RK4, 10 substeps) or, given a
    `teacher` LiftedModel, its relifted one-step map's; steps leaving the domain or the data's
    bound |x| <= 10 dropped."""
    box = rng.choice(len(BOXES), size, p=[b[2] for b in BOXES])
    low = np.array([BOXES[i][0] for i in range(len(BOXES))], dtype=float)[box]
    high = np.array([BOXES[i][1] for i in range(len(BOXES))], dtype=float)[box]
    x = rng.uniform(low, high)
    u = np.where(rng.random(size) < 1.0 / 3.0, 5.0 * (rng.random(size) < 0.5),
                 rng.uniform(0.0, 5.0, size))
    following = dynamics.rollout(x, u[:, None], dynamics.PAPER_STEP, 10)[:, 1]
    # the data's runaway bound (`SamplingConfig.max_abs_state`): beyond float32's range too
    with np.errstate(invalid='ignore'):
        keep = dynamics.in_domain(following) & np.all(np.abs(following) <= 10.0, axis=1)
    x, u, following = x[keep], u[keep], following[keep]
    if teacher is not None:
        following = teacher.step(x, u)
    return x, u, following


def one_step_loss(model, x, u, following, scale, floor):
    """Squared one-step error per component over |increment| + floor * scale (a relative
    error that stops growing where the plant barely moves; scale: the median |increment|)."""
    error = relifted_step(model, x, u) - following
    size = (following - x).abs() + floor * scale
    return ((error / size) ** 2).mean()


def rollout_loss(model, x, u, gamma, dataset_bound=10.0):
    """The relifted map iterated over windows from x_0: the state error per component over the
    model's normalisation, discounted by `gamma`, as L_rec."""
    import torch
    steps = u.shape[1]
    weights = gamma ** torch.arange(1, steps + 1, dtype=x.dtype)
    state, total = x[:, 0], 0.0
    for k in range(steps):
        # (clamped where the data's states stay: a runaway would make the gradient inf)
        state = relifted_step(model, state, u[:, k]).clamp(-dataset_bound, dataset_bound)
        total = total + weights[k] * (((state - x[:, k + 1]) / model.state_std) ** 2).mean()
    return total / weights.sum()


def student(args):
    """(torch model, KoopmanConfig): --init's, or a fresh one of --fresh's size with the
    teacher's normalisation and settings."""
    from tsr_koopman_ctrl.learning import deep_koopman
    from tsr_koopman_ctrl.model import model_file, shipped
    if args.init:
        tensors, config, metadata = model_file.load(shipped.resolve(args.init))
        return (deep_koopman.DeepKoopman.from_numpy(tensors, config),
                model_file.KoopmanConfig.of(config, metadata))
    tensors, config, metadata = model_file.load(shipped.resolve(args.teacher))
    hidden, layers, input_hidden, input_layers = args.fresh
    config = model_file.KoopmanConfig.of(config, metadata).replace(
        hidden=hidden, layers=layers, input_hidden=input_hidden, input_layers=input_layers)
    if args.lift_dim:
        config = config.replace(lift_dim=args.lift_dim)
    return (deep_koopman.DeepKoopman(config.model, tensors['state_mean'], tensors['state_std']),
            config)


def train(args, log=print):
    import torch

    from tsr_koopman_ctrl.learning.data import test_set, training_data
    from tsr_koopman_ctrl.learning.trainer import save_model, Trainer
    from tsr_koopman_ctrl.model import model_file
    from tsr_koopman_ctrl.model.lifted import LiftedModel
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    model_file.check_free(args.out, args.overwrite)
    model, config = student(args)
    config = config.replace(epochs=args.epochs, learning_rate=args.learning_rate,
                            seed=args.seed)
    teacher = (LiftedModel.load(args.teacher).astype(np.float32) if args.targets == 'teacher'
               else None)     # (float32: as koopman_nmpc evaluates it)
    data = training_data(args.data, args.trajectories, args.data_seed, log=log,
                         equilibrium_trajectories=args.equilibrium_trajectories,
                         retrieval_trajectories=args.retrieval_trajectories)
    fit, val = data.split(1.0 - config.training.validation_fraction, seed=args.seed)
    as_tensors = lambda *a: [torch.as_tensor(v, dtype=torch.float32) for v in a]  # noqa: E731
    x, u = as_tensors(fit.x, fit.u)
    vx, vu = as_tensors(val.x[:2000], val.u[:2000])
    rng = np.random.default_rng(args.seed)
    # the validation samples' targets are the plant's whatever the training targets
    val_step = as_tensors(*one_step_samples(np.random.default_rng(10_000 + args.seed), 20_000))
    # the median |increment|: its std is the stiff short tether's (272 in theta', l ~ 0)
    scale = (val_step[2] - val_step[0]).abs().median(dim=0).values
    optimiser = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimiser, T_max=args.epochs * args.batches, eta_min=config.training.final_learning_rate)

    def losses(step_batch, windows):
        step = one_step_loss(model, *step_batch, scale, args.floor)
        rollout = (rollout_loss(model, *windows, config.training.gamma) if args.weight_rollout
                   else torch.zeros(()))
        return step + args.weight_rollout * rollout, step, rollout

    def validation():
        with torch.no_grad():
            return [float(v) for v in losses(val_step, (vx, vu))]

    trainer = Trainer(config, progress=False, device='cpu')
    best, best_tensors = validation(), model.to_numpy()
    record = lambda loss, epoch: {'planner_loss': loss[0], 'one_step': loss[1],  # noqa: E731
                                  'rollout': loss[2], 'epoch': epoch, 'summed_mse': None}
    trainer.best = record(best, 0)
    log(f'init: validation {best[0]:.4g} (one step {best[1]:.4g}, rollout {best[2]:.4g})')
    begin = time.perf_counter()
    for epoch in range(args.epochs):
        sums, skipped = np.zeros(3), 0
        for _ in range(args.batches):
            windows = torch.as_tensor(rng.integers(0, len(x), args.window_batch))
            total, step, rollout = losses(
                as_tensors(*one_step_samples(rng, args.step_batch, teacher)),
                (x[windows], u[windows]))
            optimiser.zero_grad()
            total.backward()
            # a relifted rollout can run away early in a batch: clip, or Adam's step does too
            norm = torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            if not torch.isfinite(norm):
                skipped += 1
                continue
            optimiser.step()
            scheduler.step()
            sums += [total.item(), step.item(), rollout.item()]
        loss, means = validation(), sums / args.batches
        improved = loss[0] < best[0]
        if improved:
            best, best_tensors, trainer.best = loss, model.to_numpy(), record(loss, epoch + 1)
        trainer.history.append({'epoch': epoch + 1, 'planner_loss': means[0],
                                'one_step': means[1], 'rollout': means[2],
                                'val_planner_loss': loss[0]})
        log(f'epoch {epoch + 1:3d}: train {means[0]:.4g} (one step {means[1]:.4g}, rollout '
            f'{means[2]:.4g})  val {loss[0]:.4g} (one step {loss[1]:.4g}, rollout '
            f'{loss[2]:.4g}){"  (best)" if improved else ""}  {time.perf_counter() - begin:.0f} s'
            + (f', {skipped} batches skipped (non-finite gradient)' if skipped else ''))
    model.load_state_dict({k: torch.as_tensor(v) for k, v in best_tensors.items()})
    seconds = time.perf_counter() - begin
    command = 'python -m lab.distill ' + ' '.join(sys.argv[1:])
    objective = (f'relifted one-step error on fresh samples ({args.targets} targets, floor '
                 f'{args.floor}) + {args.weight_rollout} x relifted 30-step rollout')
    metadata = save_model(args.out, model, config, trainer, data,
                          test_set(5000, datasets.TEST_SEED), seconds, command,
                          {'init': args.init or f'fresh {list(args.fresh)}',
                           'teacher': args.teacher, 'objective': objective})
    log(f"saved {args.out}: best epoch {trainer.best['epoch']}, test 30-step summed MSE (lifted "
        f"linear roll) {metadata['metrics']['test']['summed_mse']:.4g}, {seconds:.0f} s")


def add_data_flags(p):
    p.add_argument('--trajectories', type=arguments.integer(0), default=40_000)
    p.add_argument('--equilibrium-trajectories', type=arguments.integer(0), default=10_000)
    p.add_argument('--retrieval-trajectories', type=arguments.integer(0), default=20_000)
    p.add_argument('--data-seed', type=arguments.SEED, default=0)


def parser():
    p = argparse.ArgumentParser(prog='distill', description=__doc__.split('\n\n')[0])
    commands = p.add_subparsers(dest='command', required=True)
    f = commands.add_parser('train', help='fine-tune on the relifted map alone')
    start = f.add_mutually_exclusive_group(required=True)
    start.add_argument('--init', help='model to fine-tune (its config)')
    start.add_argument('--fresh', type=arguments.integer(1), nargs=4,
                       metavar=('HIDDEN', 'LAYERS', 'INPUT_HIDDEN', 'INPUT_LAYERS'),
                       help="a new model of this size, the teacher's other settings")
    f.add_argument('--lift-dim', type=arguments.integer(1),
                   help="--fresh: K (default the teacher's)")
    f.add_argument('--teacher', default='koopman_retrieval')
    f.add_argument('--targets', choices=('plant', 'teacher'), default='plant',
                   help="the one-step samples' next states")
    f.add_argument('--floor', type=arguments.number(minimum=0.0), default=0.1,
                   help='relative one-step error floor, in units of the median |increment|')
    f.add_argument('--batches', type=arguments.integer(1), default=200, help='batches per epoch')
    f.add_argument('--step-batch', type=arguments.integer(1), default=4096,
                   help='fresh one-step samples per batch')
    f.add_argument('--window-batch', type=arguments.integer(1), default=128,
                   help='30-step windows per batch (the rollout term)')
    f.add_argument('--out', required=True, type=arguments.model_dir)
    arguments.add_overwrite(f)
    f.add_argument('--data', action='append', default=[], help='dataset file (repeatable)')
    add_data_flags(f)
    f.add_argument('--epochs', type=arguments.integer(1), default=10)
    f.add_argument('--learning-rate', type=arguments.number(above=0), default=3e-4)
    f.add_argument('--weight-rollout', type=arguments.number(minimum=0.0), default=1.0)
    f.add_argument('--seed', type=arguments.SEED, default=0)
    f.add_argument('--threads', type=arguments.integer(1), default=1)
    c = commands.add_parser('compare', help='prediction and closed loop, models side by side')
    c.add_argument('--model', action='append', required=True,
                   help='model directory or shipped name (repeatable; the first is the '
                   'reference of the settle-time change)')
    c.add_argument('--steps', type=arguments.integer(1), default=2000)
    c.add_argument('--out', default='out/distill')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    log = lambda text: print(text, flush=True)  # noqa: E731
    if args.command == 'train':
        train(args, log)
        return 0
    results = compare(args.model, args.steps, log)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'compare.json').write_text(json.dumps(results, indent=1) + '\n')
    (out / 'compare.md').write_text(markdown(results))
    log(markdown(results))
    return 0


if __name__ == '__main__':
    sys.exit(main())
