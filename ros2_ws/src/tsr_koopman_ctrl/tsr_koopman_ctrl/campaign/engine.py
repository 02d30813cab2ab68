"""Flying a campaign: each (run, law) one task on Dask distributed, each row kept as it ends.

    from tsr_koopman_ctrl.campaign import load_spec, run_campaign
    rows = run_campaign(load_spec('spec.yaml'), 'out/campaign')        # a local cluster
    rows = run_campaign(campaign, 'out/c', address='tcp://scheduler:8786')   # a cluster

A run is ROS-free: the law from the registry (`make_controller`) closed on the simulator's own
plant through the node's control step (`control.closed_loop`), scored by `run_figures`. The
tasks are pure functions of (campaign, run, law): a task lost with its worker is run again
elsewhere by the scheduler, and the driver writes each row once, whichever attempt finished.
Why Dask, and what was measured: docs/campaign.md.
"""

import math
import os
import time

import numpy as np

from tsr_koopman_ctrl.campaign import rows as stored
from tsr_koopman_ctrl.campaign.spec import Campaign

#: The figures a row carries, in column order, after the case's own columns; then the spec's
#: `figures` (spec.EXTRA_FIGURES), in its order.
FIGURE_COLUMNS = ('settle_tau', 'swing', 'halted', 'compute_median_ms', 'corrections',
                  'correction_sum', 'switches', 'frontier_ratio', 'error', 'run_seconds')


def extra_figures(names, figures, law, seconds, loop):
    """{name: value} of the EXTRA_FIGURES `names` of one run, its `loop` (states, tensions)
    for the trajectories (NaN, or no samples, where the run gave none: a law that gave no
    tension)."""
    from tsr_sim.dynamics import LENGTH_OFFSET
    final = figures.get('final_state')
    own = {'final_length_offset': final[LENGTH_OFFSET] if final else None,
           'compute_p99_ms': float(np.percentile(seconds, 99)) * 1e3 if seconds else None}
    trajectories = {'states': [list(map(float, x)) for x in loop[0]],
                    'tensions': [float(u) for u in loop[1]]}
    row = {}
    for name in names:
        if name == 'fallbacks':
            row[name] = int(getattr(law, 'fallbacks', 0))
            continue
        if name in trajectories:
            row[name] = trajectories[name]
            continue
        value = own[name] if name in own else figures.get(name)
        row[name] = math.nan if value is None else float(value)
    return row


def fly(campaign, run, label):
    """The row of `run` flown by the law labelled `label`: the run's number, noise seed, plant
    case (in a campaign with cases) and dispersed values, its start (x0_0..x0_3), the law, its
    figures. A law that gives no tension (a non-finite one) fails the run: `error` says why,
    `halted` is true."""
    from threadpoolctl import threadpool_limits

    from tsr_sim.dynamics import PAPER_STEP

    from tsr_koopman_ctrl.control import closed_loop, make_controller
    from tsr_koopman_ctrl.control.excitation import Excitation
    from tsr_koopman_ctrl.evaluation.figures import run_figures
    case = campaign.case(run)
    entry = campaign.law(label)
    sections = entry.settings
    row = {'run': run, 'seed': case.seed,
           **({'case': case.plant_case} if campaign.cases else {}),
           **{name: case.dispersed.get(name, math.nan) for name in campaign.dispersed_names()},
           **{f'x0_{i}': float(v) for i, v in enumerate(case.x0)}, 'law': label}
    began = time.perf_counter()
    # One thread a worker: the workers are the parallelism, BLAS pools would fight them.
    with threadpool_limits(1):
        law = make_controller(entry.law, observer=sections.get('observer'),
                              supervisor=sections.get('supervisor'),
                              safety=sections.get('safety_filter'),
                              **sections.get(entry.law, {}))
        excitation = Excitation(**sections['excitation']) if 'excitation' in sections else None
        seconds, start = [], list(case.x0)
        try:
            # As evaluation.closed_loop_figures scores a run, its loop kept for `figures`.
            loop = closed_loop(law, start, campaign.steps, plant=case.plant,
                               excitation=excitation, compute_seconds=seconds)
            figures = run_figures(np.arange(len(loop[0])) * PAPER_STEP, *loop, start=start,
                                  halted=len(loop[0]) <= campaign.steps)
            error = ''
        except ValueError as failure:
            loop = ((), ())
            figures, error = {'settle_tau': None, 'swing': math.nan, 'halted': True,
                              'frontier_ratio': None}, str(failure)

    def number(value):
        return math.nan if value is None else float(value)
    row.update({
        'settle_tau': number(figures['settle_tau']), 'swing': number(figures['swing']),
        'halted': bool(figures['halted']),
        'compute_median_ms': float(np.median(seconds)) * 1e3 if seconds else math.nan,
        'corrections': int(law.corrections), 'correction_sum': float(law.correction_sum),
        'switches': int(law.switches), 'frontier_ratio': number(figures['frontier_ratio']),
        'error': error, 'run_seconds': time.perf_counter() - began})
    row.update(extra_figures(campaign.figures, figures, law, seconds, loop))
    return row


class CampaignError(RuntimeError):
    """A campaign that could not complete (a task failed on every worker it was given)."""


def local_cluster(workers=None):
    """A local Dask cluster: `workers` processes (default: as many as cores), one thread each,
    no dashboard."""
    from dask.distributed import LocalCluster
    return LocalCluster(n_workers=workers or os.cpu_count(), threads_per_worker=1,
                        processes=True, dashboard_address=':0')


def prepare(campaign, out, resume=False):
    """Check <out> against the campaign before any run starts and store its spec: a fresh
    directory, or with `resume` one holding the same campaign (ValueError, one line,
    otherwise). Returns the (run, law) pairs still to fly."""
    spec = campaign.as_dict()
    existing = stored.read_spec(out)
    if resume:
        if existing is None:
            raise ValueError(f'--resume: {out} holds no campaign ({stored.SPEC_FILE})')
        if Campaign.parse(existing).as_dict() != Campaign.parse(spec).as_dict():
            differ = sorted(k for k in spec if spec.get(k) != existing.get(k))
            raise ValueError(f'--resume: the spec differs from the one in {out}/'
                             f'{stored.SPEC_FILE} ({", ".join(differ)}): resume it as it was, '
                             'or give another --out')
    elif existing is not None:
        raise ValueError(f'{out} holds a campaign already: --resume to complete it, or give '
                         'another --out')
    stored.write_spec(out, spec)
    stored.remove_temporaries(out)
    done = stored.finished_pairs(out)
    return [pair for pair in campaign.pairs() if pair not in done]


def run_campaign(campaign, out, *, workers=None, address=None, resume=False, progress=True,
                 client=None, report=True):
    """Fly every (run, law) of `campaign` not yet in `out` and return all its rows (a pandas
    DataFrame, also <out>/runs.parquet); then write the report (<out>/report.md) unless
    `report` is false. The engine: `client` (a dask.distributed Client), else the scheduler at
    `address`, else a local cluster of `workers` processes (default: one per core)."""
    from dask.distributed import as_completed, Client
    from tqdm import tqdm
    missing = prepare(campaign, out, resume)
    total = len(campaign.pairs())
    if missing:
        own = None
        if client is None:
            own = Client(address) if address else Client(local_cluster(workers))
        engine = client or own
        try:
            futures = [engine.submit(fly, campaign, run, label, pure=False)
                       for run, label in missing]
            with tqdm(total=total, initial=total - len(missing), unit='run', desc='campaign',
                      disable=not progress) as bar:
                for future in as_completed(futures):
                    try:
                        row = future.result()
                    except Exception as error:
                        raise CampaignError(f'a run failed on the engine: {error} (the rows '
                                            f'so far are in {out}; --resume goes on)') from None
                    stored.write_row(out, row)
                    future.release()
                    bar.update()
        finally:
            if own is not None:
                cluster = own.cluster
                own.close()
                if cluster is not None:
                    cluster.close()
    rows = stored.consolidate(out)
    if report:
        from tsr_koopman_ctrl.campaign.report import write_report
        write_report(out)
    return rows


def replay(out, run, label):
    """(the row flown again, the stored row) of `run` and the law `label` in the campaign at
    `out`: the same case from (seed, run), flown in this process."""
    spec = stored.read_spec(out)
    if spec is None:
        raise ValueError(f'{out} holds no campaign ({stored.SPEC_FILE})')
    campaign = Campaign.parse(spec, where=os.path.join(out, stored.SPEC_FILE))
    campaign.law(label)
    if not 0 <= run < campaign.runs:
        raise ValueError(f'run {run} is not in this campaign (0..{campaign.runs - 1})')
    rows = stored.read_rows(out)
    match = rows[(rows['run'] == run) & (rows['law'] == label)] if len(rows) else rows
    return fly(campaign, run, label), (match.iloc[0].to_dict() if len(match) else None)


def differences(row, other):
    """Columns where two rows of the same case differ, timing columns aside (NaN equals NaN)."""
    found = []
    for key in row:
        if key in stored.TIMING_COLUMNS:
            continue
        a, b = row[key], other.get(key)
        if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
            continue
        if isinstance(a, (list, np.ndarray)) or isinstance(b, (list, np.ndarray)):
            # A trajectory: a stored one reads back as arrays of arrays.
            same = b is not None and len(a) == len(b) and all(
                np.array_equal(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
                for x, y in zip(a, b))
            if not same:
                found.append(key)
        elif a != b:
            found.append(key)
    return found
