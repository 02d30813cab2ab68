"""Where the NMPC's step goes, both maps, offset-free included, beside a yardstick.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python lab/bench/bench_nmpc.py [--steps 400]
        [--start 0] [--set koopman_nmpc.model=models/koopman_retrieval] [--bare]
        [--model koopman_retrieval --model models/koopman_planner]

`--model` (repeatable) runs koopman_nmpc once per model, each beside its own yardstick, in
the same run (the --set settings apply to every one).

Runs each law with its offset-free observer as deployed (unless --bare), without the runtime
assurance supervisor around it (the law as deployed, supervisor included:
bench_compute.py --offset-free and the lockstep loop), on the nominal plant from a start
(default the paper's), times every call of each part of the step and prints, per step, the
median and p99 (the first step, the cold start, left out):

- shift:     the previous plan's nodes advanced one sample (one batched map call, N + 1 rows);
- intervals: every interval simulated from its node in one batch with its sensitivities
             (`map.interval`: on the physics map one call of its native build, 'native map'
             in the heading; on the learned map ~10 batched map calls on the default grid);
- condense:  the nodes affine in the tension changes (physics_nmpc: one banded solve);
- QP:        assembly and DAQP's solve;
- step:      the whole `compute`, the observer and the wrapper included;
- other:     step less the parts (observer, shift of the plan, bookkeeping).

Then, on the nodes and plan of the last step, the map alone (`advance`: the simulation without
derivatives), `interval` with exact sensitivities and with the held one-step Jacobian
('start'). The yardstick, timed in the same run before and after each law: one scalar numpy
RK4 plant step of 20 substeps (lab/bench/yardstick.py).
Every time is also given as a multiple of it (the machine's speed varies from run to run).
"""

import argparse
import os
import sys
import time

import numpy as np

from tsr_koopman_ctrl.control import closed_loop, make_controller, nmpc
from tsr_koopman_ctrl.control.offset_free import OffsetFree
from tsr_koopman_ctrl.control.registry import parse_assignments
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, HELD_OUT_STARTS

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402
from lab.bench.yardstick import seconds as yardstick  # noqa: E402

PARTS = ('shift', 'intervals', 'condense', 'QP')


def instrument(law, core, spent):
    """Wrap the parts of the NMPC `core` (`law`, or inside it) so each adds its time to the
    current step's entry of `spent`."""
    inside = []     # map.step inside map.interval is the intervals' time, not the shift's

    def timed(name, function):
        def run(*args, **kwargs):
            start = time.perf_counter()
            inside.append(name)
            try:
                return function(*args, **kwargs)
            finally:
                inside.pop()
                if spent and not (name == 'shift' and 'intervals' in inside):
                    spent[-1][name] += time.perf_counter() - start
        return run

    core.map.step = timed('shift', core.map.step)
    core.map.interval = timed('intervals', core.map.interval)
    core.solve = timed('QP', core.solve)
    compute = timed('step', law.compute)

    def step(x):
        spent.append(dict.fromkeys(PARTS + ('step',), 0.0))
        return compute(x)
    law.compute = step


def timed_call(function, repeats=50):
    function()
    start = time.perf_counter()
    for _ in range(repeats):
        function()
    return (time.perf_counter() - start) / repeats


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--steps', type=int, default=400)
    parser.add_argument('--start', type=int, default=0,
                        help='index into COMPARISON_STARTS + HELD_OUT_STARTS')
    parser.add_argument('--law', nargs='+', default=['physics_nmpc', 'koopman_nmpc'])
    parser.add_argument('--set', action='append', default=[], metavar='LAW.NAME=VALUE')
    parser.add_argument('--bare', action='store_true', help='no offset-free observer')
    parser.add_argument('--model', action='append', default=[],
                        help='koopman_nmpc on this model (repeatable: one run each)')
    add_options(parser)
    args = parser.parse_args(argv)
    say = Printed(parser, args)
    start = (COMPARISON_STARTS + HELD_OUT_STARTS)[args.start]
    overrides = {law: {} for law in args.law}
    for law, values in parse_assignments(args.set).items():   # deploy's --set, parsed alike
        if law in overrides:
            overrides[law].update(values)
    # the condensings are module functions: timed through the module
    spent = []
    condensings = {name: getattr(nmpc, name) for name in ('condense', 'condense_banded')}

    def timed(condense):
        def run(*a):
            begin = time.perf_counter()
            try:
                return condense(*a)
            finally:
                if spent:
                    spent[-1]['condense'] += time.perf_counter() - begin
        return run
    for name, condense in condensings.items():
        setattr(nmpc, name, timed(condense))

    say(f'start {list(start)}, {args.steps} steps on the nominal plant, '
        f'{"bare" if args.bare else "offset-free (default observer)"}; per step, '
        'the first (cold) step left out')
    runs = [(law_name, {}) for law_name in args.law]
    if args.model:
        runs = [run for law_name in args.law for run in (
            [(law_name, {'model': model}) for model in args.model]
            if law_name == 'koopman_nmpc' else [(law_name, {})])]
    for law_name, model in runs:
        before = yardstick()
        law = make_controller(law_name, observer='none' if args.bare else None,
                              supervisor='none', safety='none', **{**overrides[law_name], **model})
        core = law.law if isinstance(law, OffsetFree) else law
        # The physics map's native build (cached after the first run) is ready before the
        # timing, as the controller node's warm-up leaves it
        closed_loop(law, start, 5)
        core.map.compile(wait=True)
        spent.clear()
        instrument(law, core, spent)
        closed_loop(law, start, args.steps)
        after = yardstick()
        yard = 0.5 * (before + after)
        steps = spent[1:]
        table = {name: np.array([s[name] for s in steps]) for name in PARTS + ('step',)}
        table['other'] = table['step'] - sum(table[name] for name in PARTS)
        settings = core.settings
        extra = (f", sensitivities {settings.sensitivities}, {settings.precision}, model "
                 f"{settings.model}" if law_name == 'koopman_nmpc' else '')
        native = ', native map' if core.map.native() else ''
        say(f'\n{law_name} ({len(core.durations)} intervals, {core.counts.sum()} samples'
            f'{extra}{native}); yardstick {yard * 1e3:.3f} ms (before {before * 1e3:.3f}, after '
            f'{after * 1e3:.3f}); fallbacks {law.fallbacks}')
        say(f'{"part":<12}{"median ms":>10}{"p99 ms":>10}{"x yard":>8}{"p99 x yard":>12}')
        for name in PARTS + ('other', 'step'):
            values = table[name] * 1e3
            median, p99 = np.median(values), np.percentile(values, 99)
            say(f'{name:<12}{median:>10.3f}{p99:>10.3f}{median / yard / 1e3:>8.1f}'
                f'{p99 / yard / 1e3:>12.1f}')
        # the map alone and the two kinds of sensitivities, on the last step's nodes
        the_map = core.map
        interval = type(the_map).interval.__get__(the_map)     # not the timed wrapper
        nodes, plan = core.nodes[:-1], core.plan
        simulate = timed_call(lambda: the_map.advance(nodes, plan, core.counts))
        exact = timed_call(lambda: interval(nodes, plan, core.counts, exact=True), 20)
        held = timed_call(lambda: interval(nodes, plan, core.counts, exact=False))
        say(f'map alone (advance, no derivatives) {simulate * 1e3:.3f} ms '
            f'(x{simulate / yard:.1f}); interval with exact sensitivities '
            f'{exact * 1e3:.3f} ms (x{exact / yard:.1f}); with the held one-step Jacobian '
            f'{held * 1e3:.3f} ms (x{held / yard:.1f})')
    for name, condense in condensings.items():
        setattr(nmpc, name, condense)
    say.publish()


if __name__ == '__main__':
    main()
