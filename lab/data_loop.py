"""The data-driven loop, demonstrated: deploy -> record -> retrain -> redeploy, on a plant that
differs from the model.

    python -m lab.data_loop --plant actuator_weak [--rounds 2] [--out out/loop] [--page PAGE]

Every deployment is the main job's: three processes over DDS, lockstep, recorded by the recorder
node. Once, with the starting model (the shipped one): the held-out data, deployments with
excitation from the held-out starts (`evaluation.starts.HELD_OUT_STARTS`), never trained on;
and the references: the law on the nominal plant and on this plant. Then every round: deploy the
current model with excitation from the comparison starts (training bags), retrain from all
training bags so far (`learning.retraining.retrain`, fine-tuning the current model), and deploy
the new
model without excitation from the comparison starts. Offset-free control stays on throughout.
The report (<out>/<plant>/report.md, .json, rounds.png) gives per round the 30-step prediction
error on the held-out closed-loop data, the settle time, swing and integral tension. With
--page, the report goes into the page between the markers <out's name>_<plant> and the plot to
figures/<the same name>.png beside it.
"""

import argparse
import os
import sys

import numpy as np
from tsr_sim.plant import plant_parameters

from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl import arguments
from tsr_koopman_ctrl.deployment import Deployment, DeploymentError, Interrupted
from tsr_koopman_ctrl.evaluation import (COMPARISON_STARTS, HELD_OUT_STARTS,
                                         run_figures)
from tsr_koopman_ctrl.learning import multistep_errors
from tsr_koopman_ctrl.learning.recorded import DEFAULT_STEPS as WINDOW_STEPS
from tsr_koopman_ctrl.bag.checks import find_bags
from tsr_koopman_ctrl.learning.recorded import read_bags, windows_dataset
from tsr_koopman_ctrl.learning.retraining import retrain, RetrainOptions
from tsr_koopman_ctrl.control.registry import law_class
from tsr_koopman_ctrl.model import LiftedModel

from lab.report import (check_page, copy_figure, marker_name, stamp, write_into_page,
                        write_results)

EXCITATION = {'kind': 'prbs', 'amplitude': 0.3, 'hold': 20}


def deployments(args, label, model, starts, plant, excite, seed):
    """One DDS deployment per start into <out>/bags/<label>/; returns the bag paths."""
    bags = os.path.join(args.workdir, 'bags', label)
    paths = []
    for index, x0 in enumerate(starts):
        settings = {args.law: {'model': model}} if model else {}
        if excite:
            settings['excitation'] = dict(EXCITATION, seed=seed + index)
        name = f'{label}_x{index}'
        run = Deployment(args.law, settings, plant=plant, x0=x0, steps=args.steps, bags=bags,
                         name=name, logs=os.path.join(args.workdir, 'runs', name),
                         namespace=args.namespace).run()
        paths.append(run.bag)
    return paths


def loop_figures(bags):
    """Mean settle tau (None if any start did not settle), max swing, mean integral tension
    and the share of the steps the supervisor's fallback flew, read back from the bags."""
    rows, fallback, steps = [], 0, 0
    for bag in bags:
        loop = read_loop(bag)
        rows.append(run_figures(loop.tau, loop.x, loop.u[:-1], halted=loop.halted))
        fallback, steps = fallback + loop.fallback_steps, steps + len(loop.u)
    settles = [r['settle_tau'] for r in rows]
    return {'settle_tau': [s for s in settles],
            'mean_settle_tau': None if None in settles else float(np.mean(settles)),
            'swing': max(r['swing'] for r in rows),
            'tension_integral': float(np.mean([r['tension_integral'] for r in rows])),
            'fallback_share': fallback / steps if steps else 0.0}


def prediction_error(model, held_out):
    """30-step error of `model` on the held-out closed-loop windows."""
    data = windows_dataset(held_out)
    lifted = LiftedModel.load(model)
    return multistep_errors(lifted.predict(data.x[:, 0], data.u), data.x)


def run(args):
    os.makedirs(args.workdir, exist_ok=True)
    log = []
    print(f'[loop] {args.plant}: held-out data and references with {args.model}', flush=True)
    held_paths = deployments(args, 'held_out', args.model, HELD_OUT_STARTS, args.plant, True,
                             seed=1000)
    held_out, bad = read_bags(find_bags(held_paths))
    if bad:
        raise RuntimeError(f'held-out bags unusable: {bad[0]}')
    reference = {
        'nominal_plant_start_model': loop_figures(deployments(
            args, 'reference_nominal', args.model, COMPARISON_STARTS, 'nominal', False, 0)),
        'this_plant_start_model': loop_figures(deployments(
            args, 'reference_plant', args.model, COMPARISON_STARTS, args.plant, False, 0))}
    error = prediction_error(args.model, held_out)
    log.append({'round': 0, 'model': args.model, 'held_out_error': error,
                **reference['this_plant_start_model']})
    model, train_dirs = args.model, []
    for round_index in range(1, args.rounds + 1):
        label = f'round{round_index}'
        print(f'[loop] round {round_index}: excited deployments with {model}', flush=True)
        deployments(args, f'{label}_train', model, COMPARISON_STARTS, args.plant, True,
                    seed=100 * round_index)
        train_dirs.append(os.path.join(args.workdir, 'bags', f'{label}_train'))
        new_model = os.path.join(args.workdir, 'models', label)
        retrain(train_dirs, new_model, held_paths, RetrainOptions(
            init=model, epochs=args.epochs, test_trajectories=0,
            sampled_ratio=args.sampled_ratio, progress=False),
            command=f'lab.data_loop round {round_index}')
        model = new_model
        figures = loop_figures(deployments(args, f'{label}_eval', model, COMPARISON_STARTS,
                                           args.plant, False, 0))
        log.append({'round': round_index, 'model': model,
                    'held_out_error': prediction_error(model, held_out), **figures})
        print(f"[loop] round {round_index}: held-out error "
              f"{log[-1]['held_out_error']['summed_mse']:.4g}, settle "
              f"{figures['mean_settle_tau']}", flush=True)
    return {'plant': args.plant, 'law': args.law, 'start_model': args.model,
            'reference': reference, 'rounds': log}


def report(result, workdir):
    rounds, reference = result['rounds'], result['reference']
    nominal = reference['nominal_plant_start_model']['mean_settle_tau']

    def cell(value, digits=2):
        return '-' if value is None else f'{value:.{digits}f}'
    lines = [f"Data-driven loop on `{result['plant']}` with `{result['law']}` (offset-free, as "
             f"`deploy` flies it), starting from `{result['start_model']}`, {stamp()}. Settle "
             "tau: mean over the "
             f'{len(COMPARISON_STARTS)} comparison starts; the same law and start model on the '
             f'nominal plant: {cell(nominal)} tau. Prediction error: 30-step summed MSE on the '
             f'held-out closed-loop windows of this plant ({len(HELD_OUT_STARTS)} deployments '
             'from the held-out starts, never trained on). Fallback flew: the share of the '
             "steps the runtime-assurance supervisor's fallback flew (`physics_nmpc` for the "
             'NMPC) instead of the learned law.', '',
             '| round | model | held-out error (mean / median / diverged) | error vs round 0 '
             '| settle tau (mean) | per start | swing | integral u dtau | fallback flew |',
             '|---|---|---|---|---|---|---|---|---|']
    first = rounds[0]['held_out_error']['summed_mse']
    for r in rounds:
        e = r['held_out_error']
        lines.append(f"| {r['round']} | `{os.path.basename(r['model'])}` | "
                     f"{e['summed_mse']:.4g} / {e['summed_mse_median']:.4g} / "
                     f"{100 * e['diverged_fraction']:.0f}% | {first / e['summed_mse']:.2f}x "
                     f"lower | {cell(r['mean_settle_tau'])} | "
                     f"{', '.join(cell(s) for s in r['settle_tau'])} | {r['swing']:.3f} | "
                     f"{r['tension_integral']:.2f} | {100 * r['fallback_share']:.0f}% |")
    text = '\n'.join(lines) + '\n'
    write_results(workdir, 'report', result, text)
    plot_rounds(rounds, nominal, os.path.join(workdir, 'rounds.png'), result['plant'])
    print(text)
    return text


def plant_name(plant):
    """A plant's name: a variant's, or a plant file's without its folder and extension."""
    return os.path.splitext(os.path.basename(os.path.normpath(plant)))[0]


def markers(args):
    """The page markers of a loop: the --out folder's name and the plant's."""
    return f'{marker_name(args.out)}_{plant_name(args.plant)}'


def plot_rounds(rounds, nominal, path, plant):
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib import pyplot as plt
    index = [r['round'] for r in rounds]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6.4, 6.4), sharex=True)
    top.semilogy(index, [r['held_out_error']['summed_mse'] for r in rounds], 'o-')
    top.set_ylabel('held-out 30-step error')
    settle = [np.nan if r['mean_settle_tau'] is None else r['mean_settle_tau'] for r in rounds]
    bottom.plot(index, settle, 'o-', label=f'on {plant}')
    if nominal is not None:
        bottom.axhline(nominal, color='0.5', ls='--', label='start model, nominal plant')
    bottom.set_ylabel('mean settle tau')
    bottom.set_xlabel('round (0: the start model)')
    bottom.set_xticks(index)
    bottom.legend()
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    top.set_title(f'deploy -> record -> retrain -> redeploy on {plant}')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parser():
    p = argparse.ArgumentParser(prog='loop', description=__doc__.split('\n\n')[0])
    p.add_argument('--plant', required=True, help='plant variant (tsr_sim config/plants)')
    p.add_argument('--rounds', type=arguments.integer(1), default=2)
    p.add_argument('--law', default='koopman_nmpc',
                   choices=['koopman_nmpc', 'koopman_mpc', 'koopman_lqr'])
    p.add_argument('--model', help="the start model (default: the law's own)")
    p.add_argument('--steps', type=arguments.STEPS, default=2000)
    p.add_argument('--epochs', type=arguments.integer(1), default=10,
                   help='fine-tuning epochs per round')
    p.add_argument('--sampled-ratio', type=arguments.number(0), default=0.0,
                   help='sampled Table-1 trajectories per recorded window in each retraining')
    p.add_argument('--out', default=os.path.join('out', 'loop'), type=arguments.output_dir)
    p.add_argument('--namespace', help="the nodes' ROS namespace (default: the root; every "
                   'deployment has a DDS domain of its own)')
    p.add_argument('--page', default='', help='a docs page to write the report into, between '
                   "the markers <--out's name>_<plant>, and the plot to figures/ beside it")
    return p


def main(argv=None):
    p = parser()
    args = p.parse_args(argv)
    # A plant given as a file gets the directory of its name without the extension.
    args.workdir = os.path.join(args.out, plant_name(args.plant))
    # Checked before the first deployment, which takes minutes, creates anything.
    if args.model is None:
        args.model = law_class(args.law).Settings().model
    try:
        plant_parameters(args.plant)
        LiftedModel.load(args.model)
        if args.page:
            check_page(args.page, markers(args))
    except ValueError as error:
        p.error(str(error))
    if args.steps < WINDOW_STEPS:
        p.error(f'--steps {args.steps}: retraining cuts {WINDOW_STEPS}-step windows from the '
                f'deployments, which need at least that many steps')
    if os.path.isdir(args.workdir) and os.listdir(args.workdir):
        p.error(f'{args.workdir} holds an earlier loop (bags, models): give another --out or '
                'remove it')
    try:
        result = run(args)
    except Interrupted as stopped:
        print(f'loop: {stopped}; stopped, the finished rounds stay in {args.workdir}',
              file=sys.stderr)
        return arguments.INTERRUPTED_STATUS
    except (DeploymentError, RuntimeError, ValueError) as error:
        print(f'loop: {error}', file=sys.stderr)
        return 1
    text = report(result, args.workdir)
    if args.page:
        write_into_page(args.page, markers(args), text)
        copy_figure(args.page, os.path.join(args.workdir, 'rounds.png'),
                    os.path.join('figures', f'{markers(args)}.png'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
