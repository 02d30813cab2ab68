"""The worker processes of one tune command on a study: started (multiprocessing spawn), the
remaining trials shared among them, followed with a progress bar, waited for on Ctrl-C."""

import multiprocessing
from multiprocessing.connection import wait
import os
import sys

from tsr_koopman_ctrl.launcher import one_thread_children
from lab.tuning import worker
from lab.tuning.space import as_params
from lab.tuning.study import finished


def shares(remaining, jobs):
    """The remaining trials split among at most `jobs` workers, as evenly as they go."""
    count = min(jobs, remaining)
    return [remaining // count + (i < remaining % count) for i in range(count)]


def run_workers(study, spec, fixed, storage, trials, jobs=1, seed=0, progress=True):
    """Worker processes on `study` (opened by the caller, options checked) until it holds
    `trials` finished trials; RuntimeError where a worker failed (a killed one included),
    KeyboardInterrupt on Ctrl-C once the workers have stored the trials in progress."""
    from tqdm import tqdm
    if len(study.trials) == 0:
        # The law's own settings first. Enqueued here, before any worker starts: a worker that
        # checked for an empty study itself could find its sibling's first trial there.
        study.enqueue_trial(as_params(spec.law, {}, fixed, spec.also))
    remaining = trials - finished(study)
    if remaining <= 0:
        return
    # spawn: a forked child would inherit the parent's torch and Optuna state mid-use; each
    # child runs one BLAS thread (launcher.ONE_THREAD): processes side by side stall otherwise.
    context = multiprocessing.get_context('spawn')
    procs = [context.Process(target=worker.work, name=f'tune-worker-{index}', args=(
                 worker.Job(spec, fixed, storage, trials, share, seed + index, os.getpid()),))
             for index, share in enumerate(shares(remaining, jobs))]
    with one_thread_children():
        for proc in procs:
            proc.start()
    with tqdm(total=trials, desc=spec.study_name, unit='trial', file=sys.stdout,
              disable=not progress) as bar:
        try:
            while any(p.is_alive() for p in procs):
                bar.n = min(finished(study), trials)
                bar.refresh()
                # A second each, or sooner as one ends (an ended one's sentinel stays ready).
                wait([p.sentinel for p in procs if p.is_alive()], timeout=1.0)
        except KeyboardInterrupt:      # the workers got it too: they finish their trials
            print('tune: finishing the trials in progress (Ctrl-C again abandons them)',
                  file=sys.stderr, flush=True)
            for proc in procs:
                proc.join()
            raise
        bar.n = min(finished(study), trials)
        bar.refresh()
    codes = [p.exitcode for p in procs]
    if any(codes):
        raise RuntimeError(f'a tuning worker failed: exit codes {codes}')
