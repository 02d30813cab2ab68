"""Where koopman_nmpc's step goes: rollouts on the map, sensitivities, the QP.

Runs the bare law on the dynamics module from the paper's start and times, per step, every
rollout on the relifted map (`fly`: the warm start flown with feedback and each candidate plan),
the interval sensitivities (`node_gains`) and the QP (assembly and solve, less the
sensitivities it calls for). Prints the median per step of each part and its share of the
median step; the comparison is the whole step (`compute`). Single-threaded numpy is what the
law is timed with in `bench_compute.py`: run with OMP_NUM_THREADS=1.
"""

import argparse
import time

import numpy as np

from tsr_koopman_ctrl.control import closed_loop
from tsr_koopman_ctrl.control.koopman_nmpc import KoopmanNmpc
from tsr_koopman_ctrl.evaluation import PAPER_START

PARTS = ('fly', 'node_gains', 'solve')


def timed(law, spent):
    """Wrap the law's parts and its compute so each adds its time to this step's entry."""
    def wrap(name, method):
        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                spent[-1][name] += time.perf_counter() - start
        return run

    for name in PARTS:
        setattr(law, name, wrap(name, getattr(law, name)))
    compute = wrap('step', law.compute)

    def step(x):
        spent.append(dict.fromkeys(PARTS + ('step',), 0.0))
        return compute(x)
    law.compute = step


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--steps', type=int, default=100)
    args = parser.parse_args(argv)
    law = KoopmanNmpc()
    spent = []
    timed(law, spent)
    closed_loop(law, PAPER_START, args.steps)
    steps = spent[1:]       # the first step refines the LQR plan by several QP steps
    per_part = {name: np.array([s[name] for s in steps]) for name in PARTS + ('step',)}
    per_part['solve'] = per_part['solve'] - per_part['node_gains']   # solve calls node_gains
    whole = np.median(per_part['step'])
    print(f'koopman_nmpc, {len(steps)} steps from the paper start after the first, bare law, '
          'median per step')
    print(f'{"part":<32}{"median ms":>10}{"p99 ms":>10}{"x step":>8}')
    labels = {'fly': 'rollouts on the map (fly)', 'node_gains': 'sensitivities (node_gains)',
              'solve': 'QP assembly and solve', 'step': 'whole step (compute)'}
    for name in PARTS + ('step',):
        values = per_part[name] * 1e3
        print(f'{labels[name]:<32}{np.median(values):>10.1f}{np.percentile(values, 99):>10.1f}'
              f'{np.median(per_part[name]) / whole:>8.2f}')


if __name__ == '__main__':
    main()
