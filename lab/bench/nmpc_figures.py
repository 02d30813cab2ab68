"""The NMPC's closed-loop figures, both maps: what docs/nmpc.md reports.

    python lab/bench/nmpc_figures.py nominal    [--law physics_nmpc koopman_nmpc] [--bare]
    python lab/bench/nmpc_figures.py swing0.4   (theta_max 0.4)
    python lab/bench/nmpc_figures.py robustness (actuator gain 0.8..1.2, 0.05-tau lag, 1e-3 noise)
    ... [--steps 2000] [--set law.name=value ...] [--starts 0,3] [--out FILE.json]

`nominal` and `swing0.4`: from the nine comparison and held-out starts on the nominal plant:
settle tau, swing, frontier ratio at the run's own swing (and, for swing0.4, to the 0.4-rad
frontier), fallbacks, compute time per step (median, p99; the first step, the cold start, left
out) beside the yardstick (one scalar numpy RK4 plant step of 20 substeps,
lab/bench/yardstick.py), timed before and after every run.
`robustness`: offset-free (the default observer) from lab/robustness.py's six starts on the
plant with actuator gain g in (0.8, 0.9, 1.1, 1.2), a 0.05-tau actuator lag and 1e-3 sensor
noise (seed 7), and on the nominal plant: the settle tau and its ratio to the nominal one.
The law is the deployed one (`make_controller`, the offset-free observer) unless --bare.
One process, single-threaded numpy: run with OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1.
"""

import argparse
import json
import os
import sys

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.control.settings import parse_assignments
from tsr_koopman_ctrl.evaluation import (COMPARISON_STARTS, frontier_tau, HELD_OUT_STARTS,
                                         run_figures)

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.yardstick import seconds as yardstick  # noqa: E402

STARTS = COMPARISON_STARTS + HELD_OUT_STARTS
ROBUSTNESS_STARTS = COMPARISON_STARTS + HELD_OUT_STARTS[:2]   # lab/robustness.py's
GAINS = (0.8, 0.9, 1.1, 1.2)


def run(law_name, settings, start, steps, bare, plant=None):
    observer = {'disturbance': 'none'} if bare else None
    law, seconds = make_controller(law_name, observer=observer, **settings), []
    before = yardstick()
    states, tensions = closed_loop(law, start, steps, plant=plant, compute_seconds=seconds)
    after = yardstick()
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions,
                          start=start, halted=len(states) <= steps)
    ms = np.array(seconds[1:]) * 1e3
    yard = 0.5 * (before + after) * 1e3
    return {'law': law_name, 'x0': list(start), 'settings': settings, 'bare': bare,
            'plant': plant, 'settle_tau': figures['settle_tau'], 'swing': figures['swing'],
            'frontier_ratio': figures['frontier_ratio'], 'fallbacks': law.fallbacks,
            'final_state': figures['final_state'], 'cold_ms': seconds[0] * 1e3,
            'median_ms': float(np.median(ms)), 'p99_ms': float(np.percentile(ms, 99)),
            'max_ms': float(ms.max()), 'yardstick_ms': yard,
            'median_x_yardstick': float(np.median(ms)) / yard,
            'p99_x_yardstick': float(np.percentile(ms, 99)) / yard}


def fmt(value, spec='.3f'):
    return '-' if value is None else format(value, spec)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('suite', choices=('nominal', 'swing0.4', 'robustness'))
    parser.add_argument('--law', nargs='+', default=['physics_nmpc', 'koopman_nmpc'])
    parser.add_argument('--steps', type=int, default=2000)
    parser.add_argument('--bare', action='store_true', help='no offset-free observer')
    parser.add_argument('--set', action='append', default=[], metavar='LAW.NAME=VALUE')
    parser.add_argument('--starts', help='indices into the suite\'s starts, e.g. 0,3')
    parser.add_argument('--gains', help='robustness: actuator gains, e.g. 0.9,1.1')
    parser.add_argument('--out')
    args = parser.parse_args(argv)
    overrides = {law: {} for law in args.law}
    for law, values in parse_assignments(args.set).items():   # deploy's --set, parsed alike
        if law in overrides:
            overrides[law].update(values)
    if args.suite == 'swing0.4':
        for law in args.law:
            overrides[law].setdefault('theta_max', 0.4)
    starts = ROBUSTNESS_STARTS if args.suite == 'robustness' else STARTS
    if args.starts:
        starts = [starts[int(i)] for i in args.starts.split(',')]
    gains = (tuple(float(g) for g in args.gains.split(',')) if args.gains else GAINS)
    rows = []
    for law in args.law:
        for start in starts:
            plants = [None]
            if args.suite == 'robustness':
                plants += [{'actuator_gain': g, 'actuator_lag': 0.05,
                            'sensor_noise_std': [1e-3] * 4, 'seed': 7} for g in gains]
            nominal = None
            for plant in plants:
                row = run(law, overrides[law], start, args.steps, args.bare, plant)
                if plant is None:
                    nominal = row['settle_tau']
                row['nominal_settle_tau'] = nominal
                row['ratio_to_nominal'] = (None if nominal is None or row['settle_tau'] is None
                                           else row['settle_tau'] / nominal)
                if args.suite == 'swing0.4':
                    bound = frontier_tau(start, 0.4)
                    row['frontier_04_tau'] = bound
                    row['ratio_to_04_frontier'] = (None if bound is None or row['settle_tau']
                                                   is None else row['settle_tau'] / bound)
                rows.append(row)
                gain = '-' if plant is None else plant['actuator_gain']
                print(f"{law} {list(start)} gain {gain}: settle {fmt(row['settle_tau'], '.2f')} "
                      f"swing {row['swing']:.3f} ratio {fmt(row['frontier_ratio'])} "
                      f"to04 {fmt(row.get('ratio_to_04_frontier'))} "
                      f"to_nominal {fmt(row['ratio_to_nominal'])} fb {row['fallbacks']} "
                      f"ms {row['median_ms']:.2f}/{row['p99_ms']:.2f} "
                      f"yard {row['yardstick_ms']:.3f} "
                      f"(x{row['median_x_yardstick']:.1f}/x{row['p99_x_yardstick']:.1f})",
                      flush=True)
    if args.out:
        with open(args.out, 'w') as handle:
            json.dump({'suite': args.suite, 'steps': args.steps, 'bare': args.bare,
                       'rows': rows}, handle, indent=1)


if __name__ == '__main__':
    main()
