"""Reproduce the paper's Section IV-C: deep Koopman against EDMD and SINDy, and the sweeps.

``python -m lab.prediction --model koopman_default --out out/evaluation``
fits EDMD (thin-plate RBF, K centres; plain least squares and eigenvalue-clipped) and SINDy
(4th-order polynomials, pysindy) on the model's own training data (re-sampled from the settings
stored in the model), predicts 30 steps on held-out trajectories (another seed) and writes
``comparison.md``/``.json`` and ``error_vs_step.png``. ``--sweep`` also trains deep models for
each training-set size and each K (``--sweep-epochs`` each) next to EDMD (and SINDy over sizes),
writing ``sweep.md``/``.json``, ``error_vs_trajectories.png`` and ``error_vs_lift_dim.png``.
With ``--page``, the comparison's table goes into the page between the markers named after
``--out`` and its plot to ``figures/<markers>.png`` beside the page.
"""

import argparse
import dataclasses
import json
import os
import pathlib
import sys
import time

import numpy as np

from tsr_koopman_ctrl.evaluation.plots import log_plot
from tsr_koopman_ctrl.learning import baselines, errors
from tsr_koopman_ctrl.learning import dataset as datasets
from tsr_koopman_ctrl.model import DEFAULT_MODEL, lifted, model_file
from tsr_koopman_ctrl import arguments

from lab.report import check_page, copy_figure, marker_name, stamp, write_into_page


def training_data(metadata, trajectories=None):
    """Re-sample a model's training data from its provenance (optionally with another size)."""
    sampled = [p for p in metadata['data']['train'] if p.get('source') == 'sampled']
    if len(sampled) != len(metadata['data']['train']):
        raise ValueError('the model was trained on recorded data too; compare it by hand')
    fields = {f.name for f in dataclasses.fields(datasets.SamplingConfig)}
    parts = []
    for record in sampled:
        settings = {k: tuple(v) if isinstance(v, list) else v
                    for k, v in record.items() if k in fields}
        if trajectories is not None:
            settings['trajectories'] = trajectories
        parts.append(datasets.sample(datasets.SamplingConfig(**settings))[0])
    return datasets.concatenate(parts)


def fit_and_score(method, train, test):
    start = time.perf_counter()
    method.fit(train)
    seconds = time.perf_counter() - start
    return {**errors.multistep_errors(method.predict(test.x[:, 0], test.u), test.x),
            'fit_seconds': round(seconds, 1)}


def compare(model_dir, test, include_sindy=True, log=print):
    model = lifted.LiftedModel.load(model_dir)
    train = training_data(model.metadata)
    k = model.config.lift_dim
    results = {'deep_koopman': {
        **errors.multistep_errors(model.predict(test.x[:, 0], test.u), test.x),
        'fit_seconds': model.metadata.get('training_seconds')}}
    methods = [baselines.Edmd(k), baselines.Edmd(k, stabilise=True)]
    if include_sindy:
        methods.append(baselines.Sindy())
    for method in methods:
        log(f'fitting {method.name} on {len(train)} trajectories ...')
        results[method.name] = fit_and_score(method, train, test)
        log(f"  {method.name}: 30-step summed MSE {results[method.name]['summed_mse']:.4g}")
    return results, len(train)


def sweep(base_config, test, sizes, lift_dims, epochs, include_sindy=True, log=print):
    """Deep Koopman (and EDMD, SINDy) test error against training size and against K."""
    from tsr_koopman_ctrl.learning import trainer as training
    rows = []

    def deep(trajectories, k):
        config = base_config.replace(lift_dim=k, epochs=epochs)
        data, _ = datasets.sample(datasets.SamplingConfig(trajectories=trajectories))
        trainer = training.Trainer(config, progress=False)
        start = time.perf_counter()
        net = trainer.fit(data)
        score = training.evaluate(net, test, trainer.device)
        return data, {**score, 'fit_seconds': round(time.perf_counter() - start, 1)}

    for trajectories in sizes:
        data, score = deep(trajectories, base_config.model.lift_dim)
        rows.append({'sweep': 'trajectories', 'trajectories': trajectories,
                     'lift_dim': base_config.model.lift_dim, 'method': 'deep_koopman', **score})
        methods = [baselines.Edmd(base_config.model.lift_dim, stabilise=True)]
        methods += [baselines.Sindy()] if include_sindy else []
        for method in methods:
            rows.append({'sweep': 'trajectories', 'trajectories': trajectories,
                         'lift_dim': base_config.model.lift_dim, 'method': method.name,
                         **fit_and_score(method, data, test)})
        log(f'sweep: {trajectories} trajectories done')
    for k in lift_dims:
        data, score = deep(max(sizes), k)
        rows.append({'sweep': 'lift_dim', 'trajectories': max(sizes), 'lift_dim': k,
                     'method': 'deep_koopman', **score})
        rows.append({'sweep': 'lift_dim', 'trajectories': max(sizes), 'lift_dim': k,
                     'method': 'edmd_stabilised',
                     **fit_and_score(baselines.Edmd(k, stabilise=True), data, test)})
        log(f'sweep: K = {k} done')
    return rows


def error_cells(r):
    """The three figures of a prediction error: mean over the windows that did not diverge,
    median over all, fraction diverged (learning/errors.py)."""
    return (f"{r['summed_mse']:.4g} | {r['summed_mse_median']:.4g} | "
            f"{100.0 * r['diverged_fraction']:.1f}%")


ERROR_COLUMNS = 'summed MSE (30 steps, mean) | median | diverged'
SHORT_COLUMNS = 'short | rest | share'


def short_cells(r):
    """The summed MSE of the short-tether windows, of the rest, and the short ones' share."""
    split = r['short_tether']

    def cell(value, form):
        return '-' if value is None else format(value, form)

    share = '-' if split['share'] is None else f"{100.0 * split['share']:.0f}%"
    return (f"{cell(split['summed_mse'], '.4g')} | {cell(split['rest_summed_mse'], '.4g')} | "
            f'{share}')


def comparison_markdown(results, train_size, test_size):
    names = list(next(iter(results.values()))['summed_mse_per_component'])
    lines = [f'Training trajectories: {train_size}; held-out test trajectories: {test_size}; '
             '30-step prediction from the true x_0 with the recorded tensions. MSE in the '
             "paper's dimensionless state, averaged over components (and per component); "
             'means over the windows that did not diverge (|x| > 1e3 or non-finite), the '
             'median over all.', '',
             f'| method | {ERROR_COLUMNS} | MSE at step 30 | '
             + ' | '.join(f'summed {n}' for n in names)
             + f' | {SHORT_COLUMNS} | fit s |',
             '|---' * (9 + len(names)) + '|']
    for method, r in results.items():
        lines.append(f"| {method} | {error_cells(r)} | {r['final_mse']:.4g} | "
                     + ' | '.join(f"{r['summed_mse_per_component'][n]:.3g}" for n in names)
                     + f" | {short_cells(r)} | {r['fit_seconds']} |")
    short = next(iter(results.values()))['short_tether']['fraction']
    lines += ['', f'{100.0 * short:.1f}% of the test windows have a tether that dips below '
              f'l = {errors.SHORT_TETHER:g}; "short" is the mean over those, "rest" over the '
              'others, "share" the short windows\' part of the summed error.']
    return '\n'.join(lines) + '\n'


def sweep_markdown(rows):
    lines = [f'| sweep | trajectories | K | method | {ERROR_COLUMNS} | fit s |',
             '|---|---|---|---|---|---|---|---|']
    for r in rows:
        lines.append(f"| {r['sweep']} | {r['trajectories']} | {r['lift_dim']} | {r['method']} | "
                     f"{error_cells(r)} | {r['fit_seconds']} |")
    return '\n'.join(lines) + '\n'


def plot_error_vs_step(results, path):
    series = []
    for method, r in results.items():
        mse = np.asarray(r['mse_per_step'], dtype=float)
        series.append((method, np.arange(1, len(mse)), np.clip(mse[1:], 1e-12, 1e6)))
    log_plot(path, series, 'prediction step (h = 0.01 tau)', 'state MSE (clipped to 1e6)')


def plot_sweep(rows, key, xlabel, path):
    """Error against `key` ('trajectories' or 'lift_dim', also the sweep's name)."""
    selected = [r for r in rows if r['sweep'] == key]
    series = []
    for method in sorted({r['method'] for r in selected}):
        points = sorted((r[key], r['summed_mse']) for r in selected if r['method'] == method)
        series.append((method, *zip(*points)))
    log_plot(path, series, xlabel, '30-step summed state MSE', marker='o')


def parser():
    p = argparse.ArgumentParser(prog='evaluate', description=__doc__.split('\n\n')[0])
    p.add_argument('--model', default=DEFAULT_MODEL)
    p.add_argument('--out', default='out/evaluation', type=arguments.output_dir)
    p.add_argument('--test-trajectories', type=arguments.integer(1), default=5000)
    p.add_argument('--test-seed', type=int, default=datasets.TEST_SEED)
    p.add_argument('--no-sindy', action='store_true', help='skip SINDy (slowest fit)')
    p.add_argument('--sweep', action='store_true', help='also run the size and K sweeps')
    p.add_argument('--sweep-only', action='store_true', help='the sweeps, not the comparison')
    p.add_argument('--sweep-trajectories', type=arguments.integer(1), nargs='+',
                   default=[10_000, 20_000, 30_000, 40_000, 50_000, 60_000])
    p.add_argument('--sweep-lift-dims', type=arguments.integer(1), nargs='+',
                   default=[8, 16, 24, 36, 48])
    p.add_argument('--sweep-epochs', type=arguments.integer(1), default=5)
    p.add_argument('--page', default='', help='a docs page to write the comparison table into, '
                   'between the markers named after --out, and its plot to '
                   'figures/<the markers>.png beside it')
    return p


def figure_name(marker):
    """Where the plot goes, relative to the page: its figures/ folder, named after the
    markers."""
    return os.path.join('figures', f'{marker}.png')


def page_table(results, train_size, test_size, model):
    """The comparison as the page shows it: when and where it ran, then the table."""
    return (f'`{model}` against the baselines fitted on its own training data, {stamp()}. '
            + comparison_markdown(results, train_size, test_size))


def main(argv=None):
    args = parser().parse_args(argv)
    out = pathlib.Path(args.out)
    log = lambda text: print(text, flush=True)  # noqa: E731
    try:
        if args.page:
            if args.sweep_only:
                raise ValueError('--page takes the comparison table; the sweep writes none')
            check_page(args.page, marker_name(args.out))
        lifted.LiftedModel.load(args.model)     # a bad model is one line, before any work
        test, _ = datasets.sample(datasets.SamplingConfig(trajectories=args.test_trajectories,
                                                          seed=args.test_seed))
        if not args.sweep_only:
            results, train_size = compare(args.model, test, not args.no_sindy, log)
    except (ValueError, model_file.ModelFileError) as error:
        print(f'evaluate: {error}', file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)     # made once the model has loaded, not before
    if not args.sweep_only:
        (out / 'comparison.json').write_text(json.dumps(results, indent=1) + '\n')
        (out / 'comparison.md').write_text(comparison_markdown(results, train_size, len(test)))
        plot_error_vs_step(results, out / 'error_vs_step.png')
        log((out / 'comparison.md').read_text())
        if args.page:
            write_into_page(args.page, marker_name(args.out),
                            page_table(results, train_size, len(test), args.model))
            copy_figure(args.page, out / 'error_vs_step.png',
                        figure_name(marker_name(args.out)))
    if args.sweep or args.sweep_only:
        model = lifted.LiftedModel.load(args.model)
        config = model_file.KoopmanConfig.of(model.config, model.metadata)
        rows = sweep(config, test, args.sweep_trajectories, args.sweep_lift_dims,
                     args.sweep_epochs, not args.no_sindy, log)
        (out / 'sweep.json').write_text(json.dumps(rows, indent=1) + '\n')
        (out / 'sweep.md').write_text(sweep_markdown(rows))
        plot_sweep(rows, 'trajectories', 'training trajectories',
                   out / 'error_vs_trajectories.png')
        plot_sweep(rows, 'lift_dim', 'K (learned observables)', out / 'error_vs_lift_dim.png')
        log((out / 'sweep.md').read_text())
    log(f'written to {out}/')
    return 0


if __name__ == '__main__':
    sys.exit(main())
