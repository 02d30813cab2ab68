"""The report of a study: its best settings and the law's own scored on the tuning starts and
on the held-out ones (`HELD_OUT_STARTS`, which the tuning never saw), written as
<out>/<study>.json and .md."""

import os

from tsr_koopman_ctrl.evaluation import HELD_OUT_STARTS
from lab.report import write_results
from lab.tuning.scoring import OBJECTIVES, score
from lab.tuning.space import as_json, from_json
from lab.tuning.study import finished


def quiet(*args, **kwargs):
    pass


def run_scorings(scorings, jobs, say=print):
    """{key: score(*arguments)} for {key: arguments}, in `jobs` processes, a line as each ends
    (the report of a slow law is minutes: koopman_nmpc's took 22 on one core and 21 in two
    processes; why two were no faster is not known. Each child runs one BLAS
    thread, launcher.ONE_THREAD: with numpy's default, processes side by side stall)."""
    from concurrent.futures import as_completed, ProcessPoolExecutor
    import multiprocessing
    from tsr_koopman_ctrl.launcher import one_thread_children
    jobs = min(jobs, len(scorings))
    say(f'scoring the default and the best settings on the tuning and the held-out starts '
        f'({len(scorings)} scorings, {jobs} process(es))', flush=True)
    results = {}
    if jobs == 1:
        for key, arguments in scorings.items():
            results[key] = score(*arguments)
            say(f'  {key}: {results[key][0]:.3f} ({len(results)}/{len(scorings)})', flush=True)
        return results
    # spawn: a forked child would inherit the parent's torch and Optuna state mid-use.
    with one_thread_children():
        pool = ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context('spawn'))
        try:
            futures = {pool.submit(score, *arguments): key
                       for key, arguments in scorings.items()}
            for future in as_completed(futures):
                results[futures[future]] = future.result()
                say(f'  {futures[future]}: {future.result()[0]:.3f} '
                    f'({len(results)}/{len(scorings)})', flush=True)
        finally:    # on an error, the scorings not yet started do not start
            pool.shutdown(cancel_futures=True)
    return {key: results[key] for key in scorings}     # the report's order


def report(study, spec, fixed, out, jobs=1, say=print):
    """(summary, text, [json path, md path]) of `study`, written in `out`."""
    best = study.best_trial
    settings = from_json(best.user_attrs['settings'])
    scorings = {f'{label}_{tag}': (spec.law, values, starts, spec.swing_max, spec.steps,
                                   spec.objective, spec.graded)
                for label, starts in (('tuning', spec.tuning_starts),
                                      ('held_out', HELD_OUT_STARTS))
                for tag, values in (('default', dict(fixed)), ('tuned', settings))}
    results = {key: {'score': value, 'runs': runs}
               for key, (value, runs) in run_scorings(scorings, jobs, say).items()}
    summary = {'law': spec.law, 'study': spec.study_name, 'trials': finished(study),
               'swing_max': spec.swing_max, 'objective': spec.objective,
               'penalty': spec.penalty, 'starts': spec.starts, 'fixed': list(spec.fix),
               'also': list(spec.also),
               'best_value': best.value,
               'best_settings': as_json(settings),
               'tuning_starts': [list(s) for s in spec.tuning_starts],
               'held_out_starts': [list(s) for s in HELD_OUT_STARTS], 'results': results}
    _, penalty, _, score_name = OBJECTIVES[spec.objective]
    lines = [f"{spec.law}: {summary['trials']} trials, best score {best.value:.3f} "
             f'({score_name}) on the tuning starts (swing <= '
             f'{spec.swing_max:g} rad)', f"best settings: {summary['best_settings']}", '']
    if best.value >= penalty:
        closest = ('the trial that missed least' if spec.graded
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
    write_results(out, spec.study_name, summary, text)
    files = [os.path.join(out, spec.study_name + suffix) for suffix in ('.json', '.md')]
    return summary, text, files


def ratio_text(figures):
    return '-' if figures.get('frontier_ratio') is None else f"{figures['frontier_ratio']:.2f}x"
