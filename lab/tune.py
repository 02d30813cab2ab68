"""Tune a law's settings with Optuna, the same way for every law, and score it on held-out starts.

    python -m lab.tune --law linear_lqr [--trials 60] [--jobs 2]
        [--storage out/tune/linear_lqr.journal | postgresql://...] [--swing-max 0.8]
        [--fix SETTING=VALUE] [--also SETTING] [--objective settle|ratio|worst-ratio|swing]
        [--penalty flat|graded] [--starts comparison|swing]

The search space is each setting's `tune` entry in its law's Settings class (the one declaration).
A trial closes the law on the dynamics module (step-identical to the DDS loop) from every tuning
start (`evaluation.starts.COMPARISON_STARTS`; with `--starts swing` also `SWING_TUNING_STARTS`, two
starts with an initial swing like the held-out ones) and scores, per --objective, the mean settle
time into the 1% zone ('settle', the default), the mean frontier ratio ('ratio': settle time over
the minimum time at the run's own swing, `evaluation.frontier`, so a law gains nothing by swinging
wider), the largest frontier ratio ('worst-ratio': the issue's targets are "from every start") or
the largest swing ('swing': can any setting hold a bound at all); a start that does not settle,
halts, or swings beyond --swing-max scores PENALTY_TAU (settle) or PENALTY_RATIO, flat by default;
with `--penalty graded` the penalty grows with how far the run missed (radians past the swing
bound, plus one if it did not settle), so a search whose first trials all miss still learns which
way is better. A study that never scored under the penalty says so in its report. A study keeps the
objective, the penalty and the tuning starts it was started with. The law's own settings are the
first trial, so tuning never reports worse than the default. The study lives in Optuna's storage: a
journal file here (several processes share it: --jobs starts them; a second command with another
--seed adds workers), a database URL where users have a server; running the command again resumes
it up to --trials in total. At the end the best settings are scored on the held-out starts
(`HELD_OUT_STARTS`), which the tuning never saw, in --jobs processes, and written to
<out>/<study>.json and .md.
`--fix` holds a setting out of the search: koopman_lqr's q only counts with state_weight
'state', and a joint search samples that form a few times only (4 of 60 trials, docs/tuning.md).
`--also` adds a setting the default search leaves out: `q_cross`, the cross terms of the
quadratic-cost laws' state weight (six more dimensions).
"""

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np

from tsr_koopman_ctrl.control import CONTROLLERS, make_controller
from tsr_koopman_ctrl.control.registry import law_class
from tsr_koopman_ctrl.control.settings import fields, parse_value
from tsr_koopman_ctrl.evaluation import closed_loop_figures, COMPARISON_STARTS, HELD_OUT_STARTS
from tsr_koopman_ctrl.evaluation.starts import SWING_TUNING_STARTS
from tsr_koopman_ctrl.model import LiftedModel
from tsr_koopman_ctrl.commands import cli
from tsr_koopman_ctrl.launcher import child_environment, one_thread_children
from lab.report import write_results

#: Score of a start that does not settle, halts or swings too far: twice the 20-tau run.
PENALTY_TAU = 40.0
#: The same for the ratio objectives: ten times the minimum time.
PENALTY_RATIO = 10.0
#: A run that does not settle under the 'swing' objective (a tumble is beyond pi anyway).
PENALTY_SWING = 10.0
#: A graded miss counts at most this much above the penalty (a law that cannot be built).
MISS_CAP = 10.0
#: objective -> (figure a start scores, its penalty, how the starts' scores combine, the
#: score's name in the report)
OBJECTIVES = {'settle': ('settle_tau', PENALTY_TAU, 'mean', 'mean settle tau'),
              'ratio': ('frontier_ratio', PENALTY_RATIO, 'mean', 'mean frontier ratio'),
              'worst-ratio': ('frontier_ratio', PENALTY_RATIO, 'max', 'largest frontier ratio'),
              'swing': ('swing', PENALTY_SWING, 'max', 'largest swing [rad]')}
#: --starts -> the tuning starts a trial deploys from (never a held-out one).
TUNING_STARTS = {'comparison': COMPARISON_STARTS,
                 'swing': COMPARISON_STARTS + SWING_TUNING_STARTS}


def tunable(law, also=()):
    """[(setting, default, tune spec)] of a law: the settings searched by default and those
    named in `also` (searched only when asked, e.g. q_cross)."""
    return [(name, default, meta['tune']) for name, default, meta in
            fields(law_class(law).Settings) if meta.get('tune') is not None
            and (meta.get('searched', True) or name in also)]


def suggest(trial, law, fixed=None, also=()):
    """Settings of a trial, sampled from each setting's `tune` entry; `fixed`: {setting: value}
    held out of the search; `also`: settings searched only when asked."""
    settings = dict(fixed or {})
    for name, default, spec in tunable(law, also):
        if name in settings:
            continue
        if isinstance(spec, list) and spec and isinstance(spec[0], str):
            settings[name] = trial.suggest_categorical(name, spec)
        elif isinstance(default, tuple):
            specs = spec if isinstance(spec, list) else [spec] * len(default)
            settings[name] = tuple(number(trial, f'{name}_{i}', s) for i, s in enumerate(specs))
        else:
            settings[name] = number(trial, name, spec, integer=isinstance(default, int))
    return settings


def number(trial, name, spec, integer=False):
    low, high, scale = spec
    if integer:
        return trial.suggest_int(name, int(low), int(high), log=scale == 'log')
    return trial.suggest_float(name, low, high, log=scale == 'log')


def as_params(law, settings, fixed=None, also=()):
    """The inverse of `suggest`: Optuna parameters of given settings (to enqueue a trial)."""
    params = {}
    for name, default, spec in tunable(law, also):
        if name in (fixed or {}):
            continue
        value = settings.get(name, default)
        if isinstance(value, tuple):
            params.update({f'{name}_{i}': v for i, v in enumerate(value)})
        else:
            params[name] = value
    return params


def score(law, settings, starts, swing_max, steps, objective='settle', graded=False):
    """(score over starts per `objective`, per-start figures), the law built as the node builds
    it (offset-free by default). A law that cannot be built scores the penalty everywhere
    (`graded`: plus MISS_CAP); with `graded` a start that misses scores the penalty plus
    `miss`."""
    figure, penalty, combine, _ = OBJECTIVES[objective]
    try:
        controller = make_controller(law, **settings)
    except ValueError as error:
        return penalty + (MISS_CAP if graded else 0.0), [{'error': str(error)}] * len(starts)
    bound = None if figure == 'swing' else swing_max   # 'swing': how far, whatever the bound
    runs, scores = [], []
    for start in starts:
        figures = closed_loop_figures(controller, start, steps)
        missed = miss(figures, bound)
        if missed == 0.0 and figures[figure] is not None:
            scores.append(figures[figure])
        else:   # (a settled run of a start without a tabulated frontier has no ratio)
            scores.append(penalty + (missed if graded else 0.0))
        runs.append(figures)
    return (max(scores) if combine == 'max' else sum(scores) / len(scores)), runs


def miss(figures, swing_max=None):
    """How far a run missed: radians past `swing_max` (None: no bound) plus one if it did not
    settle, at most MISS_CAP; 0.0 for a run that counts."""
    past = 0.0 if swing_max is None else max(0.0, figures['swing'] - swing_max)
    unsettled = 1.0 if figures['settle_tau'] is None else 0.0
    total = past + unsettled
    return MISS_CAP if not np.isfinite(total) else min(total, MISS_CAP)


def study_name(args):
    # A fixed value may be a path ('model=models/x'): only safe characters go into file names.
    fixed = ''.join('_' + re.sub(r'[^A-Za-z0-9.-]+', '-', text.replace('=', '-'))
                    for text in args.fix)
    fixed += ''.join(f'_with-{name}' for name in args.also)
    objective = '' if args.objective == 'settle' else '_' + args.objective
    penalty = '' if args.penalty == 'flat' else '_' + args.penalty
    starts = '' if args.starts == 'comparison' else f'_{args.starts}-starts'
    return (args.study
            or f'{args.law}{fixed}{objective}{penalty}{starts}_swing{args.swing_max:g}')


def fixed_settings(args):
    """{setting: value} of the --fix options, checked against the law's settings."""
    settings = law_class(args.law).Settings
    pairs = [text.split('=', 1) for text in args.fix]
    if any(len(pair) != 2 for pair in pairs):
        raise ValueError(f'--fix takes SETTING=VALUE, got {args.fix}')
    fixed = {name: parse_value(settings, name, value) for name, value in pairs}
    # Out of range, not a choice, the wrong length, a model that does not load: one line now
    # rather than 60 trials that all score the penalty.
    settings(**fixed)
    if 'model' in fixed:
        LiftedModel.load(fixed['model'])
    searchable = {name for name, _, meta in fields(settings) if meta.get('tune') is not None}
    for name in args.also:
        if name not in searchable:
            raise ValueError(f'--also {name}: {args.law} has no such searchable setting; '
                             f'searchable: {sorted(searchable)}')
    return fixed


def check_journal(storage):
    """A journal file given as --storage must be absent, empty or a journal: Optuna would
    append its records to any other file before failing."""
    if '://' in storage or not os.path.isfile(storage) or os.path.getsize(storage) == 0:
        return
    with open(storage, 'rb') as stream:
        first = stream.readline(1 << 16)
    try:
        record = json.loads(first)
    except ValueError:
        record = None
    is_journal = isinstance(record, dict) and 'op_code' in record
    if not is_journal:
        raise ValueError(f'--storage {storage} is not an Optuna journal file; nothing was '
                         'written to it')


def open_study(args):
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if '://' in args.storage:
        storage = args.storage
    else:
        os.makedirs(os.path.dirname(os.path.abspath(args.storage)), exist_ok=True)
        storage = JournalStorage(JournalFileBackend(args.storage))
    sampler = optuna.samplers.TPESampler(seed=args.seed + args.worker)
    if study_name(args) in optuna.study.get_all_study_names(storage):
        # Loaded, not created again: create_study(load_if_exists=True) appends a record to a
        # journal even when the study is there, so a refused resume changed the file.
        study = optuna.load_study(study_name=study_name(args), storage=storage, sampler=sampler)
    else:
        study = optuna.create_study(study_name=study_name(args), storage=storage,
                                    direction='minimize', load_if_exists=True, sampler=sampler)
    # A study holds one objective: settle times and ratios in one study would be compared.
    # Studies from before --penalty and --starts have no such attribute: they were flat and
    # tuned on the comparison starts.
    for option, default in (('objective', None), ('penalty', 'flat'), ('starts', 'comparison')):
        recorded = study.user_attrs.get(option, default if study.trials else None)
        if recorded is None:
            study.set_user_attr(option, getattr(args, option))
        elif recorded != getattr(args, option):
            raise ValueError(f'study {study_name(args)!r} was tuned on --{option} {recorded}, '
                             f'not {getattr(args, option)}')
    return study


def worker(args):
    """Run trials until the study holds --trials finished ones."""
    import optuna
    from optuna.study import MaxTrialsCallback
    study = open_study(args)
    states = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL)

    def objective(trial):
        settings = suggest(trial, args.law, args.fixed, args.also)
        value, runs = score(args.law, settings, TUNING_STARTS[args.starts], args.swing_max,
                            args.steps, args.objective, args.penalty == 'graded')
        trial.set_user_attr('settings', {k: list(v) if isinstance(v, tuple) else v
                                         for k, v in settings.items()})
        trial.set_user_attr('settle', [r.get('settle_tau') for r in runs])
        trial.set_user_attr('swing', [r.get('swing') for r in runs])
        return value

    if finished(study) < args.trials:
        # Ctrl-C reaches the workers too (one process group): the first lets the trial in
        # progress finish and be stored, a second abandons it (the parent says which).
        requested = []

        def on_interrupt(signum, frame):
            if requested:
                raise KeyboardInterrupt
            requested.append(signum)
        signal.signal(signal.SIGINT, on_interrupt)
        try:
            study.optimize(objective, callbacks=[MaxTrialsCallback(args.trials, states=states),
                                                 stop_when(requested, os.getppid())])
        except KeyboardInterrupt:
            pass


def stop_when(requested, parent):
    """An Optuna callback that stops the worker after its current trial when a stop was
    `requested` (a list that is not empty) or `parent`, the tune command that started it, is
    gone: a killed command must not leave its workers running unseen."""
    def check(study, trial):
        if requested or os.getppid() != parent:
            study.stop()
    return check


def finished(study):
    import optuna
    done = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL)
    return sum(t.state in done for t in study.get_trials(deepcopy=False))


def run_workers(args, argv, study):
    """--jobs processes on the one `study` (opened by main), with a progress bar over its
    finished trials."""
    from tqdm import tqdm
    if len(study.trials) == 0:
        # The law's own settings first. Enqueued here, before any worker starts: a worker that
        # checked for an empty study itself could find its sibling's first trial there.
        study.enqueue_trial(as_params(args.law, {}, args.fixed, args.also))
    procs = [subprocess.Popen([sys.executable, '-m', 'lab.tune', *argv,
                               '--worker', str(i)], env=child_environment())
             for i in range(args.jobs)]
    with tqdm(total=args.trials, desc=study_name(args), unit='trial', file=sys.stdout) as bar:
        try:
            while any(p.poll() is None for p in procs):
                bar.n = min(finished(study), args.trials)
                bar.refresh()
                time.sleep(1.0)
        except KeyboardInterrupt:      # the workers got it too: they finish their trials
            print('tune: finishing the trials in progress (Ctrl-C again abandons them)',
                  file=sys.stderr, flush=True)
            for proc in procs:
                proc.wait()
            raise
        bar.n = min(finished(study), args.trials)
        bar.refresh()
    if any(p.returncode for p in procs):
        raise RuntimeError(f'a tuning worker failed: exit codes {[p.returncode for p in procs]}')
    return study


def run_scorings(scorings, jobs):
    """{key: score(*arguments)} for {key: arguments}, in `jobs` processes, a line as each ends
    (the report of a slow law is minutes: koopman_nmpc's took 22 on one core and 21 in two
    processes; why two were no faster is not known. Each child runs one BLAS
    thread, launcher.ONE_THREAD: with numpy's default, processes side by side stall)."""
    from concurrent.futures import as_completed, ProcessPoolExecutor
    import multiprocessing
    jobs = min(jobs, len(scorings))
    print(f'scoring the default and the best settings on the tuning and the held-out starts '
          f'({len(scorings)} scorings, {jobs} process(es))', flush=True)
    results = {}
    if jobs == 1:
        for key, arguments in scorings.items():
            results[key] = score(*arguments)
            print(f'  {key}: {results[key][0]:.3f} ({len(results)}/{len(scorings)})', flush=True)
        return results
    # spawn: a forked child would inherit the parent's torch and Optuna state mid-use.
    with one_thread_children():
        pool = ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context('spawn'))
        try:
            futures = {pool.submit(score, *arguments): key
                       for key, arguments in scorings.items()}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                print(f'  {futures[future]}: {future.result()[0]:.3f} '
                      f'({len(results)}/{len(scorings)})', flush=True)
        finally:    # on an error, the scorings not yet started do not start
            pool.shutdown(cancel_futures=True)
    return {key: results[key] for key in scorings}     # the report's order


def report(args, study):
    best = study.best_trial
    settings = {k: tuple(v) if isinstance(v, list) else v
                for k, v in best.user_attrs['settings'].items()}
    scorings = {f'{label}_{tag}': (args.law, values, starts, args.swing_max, args.steps,
                                   args.objective, args.penalty == 'graded')
                for label, starts in (('tuning', TUNING_STARTS[args.starts]),
                                      ('held_out', HELD_OUT_STARTS))
                for tag, values in (('default', dict(args.fixed)), ('tuned', settings))}
    results = {key: {'score': value, 'runs': runs}
               for key, (value, runs) in run_scorings(scorings, args.jobs).items()}
    summary = {'law': args.law, 'study': study_name(args), 'trials': finished(study),
               'swing_max': args.swing_max, 'objective': args.objective,
               'penalty': args.penalty, 'starts': args.starts, 'fixed': args.fix,
               'also': args.also,
               'best_value': best.value,
               'best_settings': {k: list(v) if isinstance(v, tuple) else v
                                 for k, v in settings.items()},
               'tuning_starts': [list(s) for s in TUNING_STARTS[args.starts]],
               'held_out_starts': [list(s) for s in HELD_OUT_STARTS], 'results': results}
    _, penalty, _, score_name = OBJECTIVES[args.objective]
    lines = [f"{args.law}: {summary['trials']} trials, best score {best.value:.3f} "
             f'({score_name}) on the tuning starts (swing <= '
             f'{args.swing_max:g} rad)', f"best settings: {summary['best_settings']}", '']
    if best.value >= penalty:
        closest = ('the trial that missed least' if args.penalty == 'graded'
                   else 'only the first such trial')
        lines[-1:-1] = [f'No trial scored under the penalty ({penalty:g}) from every tuning '
                        f'start: the "best settings" are {closest}.']
    lines += [
             '| starts | settings | settle tau per start (swing, frontier ratio) | score |',
             '|---|---|---|---|']
    for key, result in results.items():
        cells = ', '.join('-' if r.get('settle_tau') is None else
                          f"{r['settle_tau']:.2f} ({r['swing']:.2f}, {ratio_text(r)})"
                          for r in result['runs'])
        label, tag = key.split('_', 1) if key.startswith('tuning') else ('held-out', key[9:])
        lines.append(f"| {label} | {tag} | {cells} | {result['score']:.3f} |")
    text = '\n'.join(lines) + '\n'
    write_results(args.out, study_name(args), summary, text)
    print(text)


def ratio_text(figures):
    return '-' if figures.get('frontier_ratio') is None else f"{figures['frontier_ratio']:.2f}x"


def parser():
    p = argparse.ArgumentParser(prog='tune', description=__doc__.split('\n\n')[0])
    p.add_argument('--law', required=True, choices=sorted(CONTROLLERS))
    p.add_argument('--trials', type=cli.integer(1), default=60,
                   help='finished trials in the study')
    p.add_argument('--jobs', type=cli.integer(1), default=1,
                   help='worker processes on the study (and for its final report)')
    p.add_argument('--storage', help='journal file or database URL '
                   '(default: <out>/<study>.journal)')
    p.add_argument('--study', help='study name (default: <law>[_<fixed settings>]'
                   '[_<objective>]_swing<swing-max>)')
    p.add_argument('--objective', choices=sorted(OBJECTIVES), default='settle',
                   help="what a trial minimises over the tuning starts: mean settle time, mean "
                   "or largest frontier ratio at the run's own swing, or the largest swing "
                   "(a run that does not settle scores the penalty)")
    p.add_argument('--penalty', choices=('flat', 'graded'), default='flat',
                   help="a start that misses (does not settle, swings past --swing-max) "
                   "scores the penalty ('flat') or the penalty plus how far it missed: radians "
                   "past the bound, plus one if it did not settle ('graded')")
    p.add_argument('--starts', choices=sorted(TUNING_STARTS), default='comparison',
                   help="the tuning starts: the four comparison starts ('comparison'), or those "
                   "and two with an initial swing ('swing'); the held-out starts never")
    p.add_argument('--swing-max', type=cli.number(above=0), default=0.8,
                   help='largest |theta| a run may reach and still count as settled [rad]')
    p.add_argument('--steps', type=cli.STEPS, default=2000)
    p.add_argument('--seed', type=cli.SEED, default=0)
    p.add_argument('--out', default=os.path.join('out', 'tune'), type=cli.output_dir)
    p.add_argument('--fix', action='append', default=[], metavar='SETTING=VALUE',
                   help='hold a setting at a value instead of tuning it (repeatable; e.g. '
                   'state_weight=state for koopman_lqr)')
    p.add_argument('--also', action='append', default=[], metavar='SETTING',
                   help='search a setting that is left out by default (repeatable; e.g. '
                   "q_cross: the state weight's cross terms)")
    p.add_argument('--worker', type=int, default=None, help=argparse.SUPPRESS)
    return p


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser().parse_args(argv)
    args.storage = args.storage or os.path.join(args.out, study_name(args) + '.journal')
    try:
        args.fixed = fixed_settings(args)
        check_journal(args.storage)
        if args.worker is None:        # a study tuned on another objective: refused here
            args.worker = 0
            study = open_study(args)
        else:
            worker(args)
            return 0
    except ValueError as error:
        print(f'tune: {error}', file=sys.stderr)
        return 2
    try:
        study = run_workers(args, argv, study)
    except KeyboardInterrupt:
        print(f'tune: interrupted; {args.storage} keeps the finished trials: the same command '
              'resumes the study', file=sys.stderr)
        return cli.INTERRUPTED_STATUS
    except (RuntimeError, ValueError) as error:
        print(f'tune: {error}', file=sys.stderr)
        return 1
    report(args, study)
    return 0


if __name__ == '__main__':
    sys.exit(main())
