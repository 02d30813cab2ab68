"""The timed loop rehearsed ROS-free: the plant advances one sample a period whatever the law
does, as `sim_node` in `mode: timed` and a real plant do, and the law answers the newest state
when its compute (measured, wall clock) is done.

    python -m lab.timed_rehearsal [--slowdown 1 1.5 2] [--rate 100] [--steps 800]
        [--set koopman_nmpc.theta_max=0.4 ...] [--against physics_nmpc]
        [--out lab/results/timed_rehearsal]

What the node does, step for step (`controller_node`, docs/supervisor.md): the law computes
for the newest state k; meanwhile the plant flies the command it has; the new command applies
from the first sample after the compute ends; the states that arrived meanwhile but the newest
are dropped and the law told how many samples passed (`ControlStep(x, elapsed)`). The first
command of a run starts its clock (`clock_start: command`). `--slowdown` multiplies every
measured compute (2: a machine half as fast, or a loaded one), so what a slower host would do
is seen on this one. `--set` gives the law's settings as deploy's does (the swing bound, say:
each cell then also gives the run's largest |theta|). `--against` flies a verified law alone
from the same starts at the same speeds: under the table, per speed, the runs lost where it
alone holds. Writes timed_rehearsal.md and .json
into --out and the table into docs/supervisor.md between its markers.
"""

import argparse
import math
import os
import shlex
import sys

import numpy as np
from tsr_sim import dynamics
from tsr_sim.plant import config_from_parameters, Plant, Status
from tsr_sim.units import Scale

from lab.report import check_page, marker_name, publish, stamp
from tsr_koopman_ctrl.control import make_controller, TensionLimiter
from tsr_koopman_ctrl.control.registry import parse_assignments
from tsr_koopman_ctrl.control.step import ControlStep
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, HELD_OUT_STARTS, run_figures
from tsr_koopman_ctrl.evaluation.figures import SWING_TOLERANCE

STARTS = COMPARISON_STARTS + HELD_OUT_STARTS
PAGE = os.path.join('docs', 'supervisor.md')


def timed_loop(law, x0, steps, rate_hz=100.0, slowdown=1.0, compute_periods=None):
    """`law` against a plant advancing `rate_hz` samples a second for `steps` samples: (states
    (k + 1, n), {'dropped', 'overruns', 'longest' (periods, after the first), 'lost'}); the
    run ends early (lost) when the plant leaves the domain or |theta| passes pi.
    `compute_periods(result)`: each step's compute in periods (default: the measured one
    times `slowdown`)."""
    scale = Scale()
    period = 1.0 / rate_hz
    if compute_periods is None:
        def compute_periods(result):
            return result.compute_seconds * slowdown / period
    plant = Plant(config_from_parameters(
        {'initial_state': [float(v) for v in x0], 'step': dynamics.PAPER_STEP, 'substeps': 10},
        scale))
    step = ControlStep(law, TensionLimiter(dynamics.TENSION_LIMIT))
    step.reset()
    states = [plant.state.copy()]
    pending = []            # (first sample it applies from, tension [N]), oldest first
    command = None
    last, clock = None, 0.0
    figures = {'dropped': 0, 'overruns': 0, 'longest': 0.0, 'lost': False}
    while True:
        newest = max(int(math.floor(clock + 1e-9)), 0 if last is None else last + 1)
        clock = max(clock, newest)
        while len(states) <= min(newest, steps):    # the plant runs on under what it has
            sample = len(states) - 1
            while pending and pending[0][0] <= sample:
                command = pending.pop(0)[1]
            plant.advance(command)
            states.append(plant.state.copy())
            if plant.status is Status.HALTED_OUT_OF_DOMAIN or abs(plant.state[0]) > np.pi:
                figures['lost'] = True
                return np.array(states), figures
        if newest >= steps:
            return np.array(states[:steps + 1]), figures
        elapsed = 1 if last is None else newest - last
        result = step(scale.state_from_si(plant.config.scale.state_to_si(plant.measure())),
                      elapsed)
        tension = scale.u_to_tension(result.tension)       # (NaN: no command sent)
        if last is None:
            command = tension           # the first command starts the clock
        else:
            took = compute_periods(result)
            figures['dropped'] += elapsed - 1
            figures['overruns'] += took > 1.0
            figures['longest'] = max(figures['longest'], took)
            clock += took
            # sample s is advanced at tick s + 1 under the newest command the plant has
            if math.isfinite(tension):
                pending.append((int(math.ceil(clock)) - 1, tension))
        last = newest


def fly(start, slowdown, rate_hz, steps, law):
    law.reset()
    states, loop = timed_loop(law, start, steps, rate_hz, slowdown)
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states,
                          np.zeros(len(states)), start=start, halted=loop['lost'])
    return {'start': list(start), 'slowdown': slowdown, 'ratio': figures['frontier_ratio'],
            'swing': figures['swing'], 'switches': law.switches, **loop}


def cell(row, swing=False):
    if row['lost']:
        return 'lost'
    ratio = 'not settled' if row['ratio'] is None else f"{row['ratio']:.3f}x"
    return (f"{ratio}" + (f", swing {row['swing']:.3f}" if swing else '')
            + f", {row['dropped']} dropped, longest {row['longest']:.1f}, "
            f"{row['switches']} switches")


def held(row, limit):
    """A run held: in the domain and, flown under a swing bound, within `limit` [rad]."""
    return not row['lost'] and (limit is None or row['swing'] <= limit)


def summary(rows, reference, slowdowns, against, limit):
    """Lines under the table, per speed: the runs lost (past the bound, with one), the
    longest step, and where `against` flew too, the runs lost where it alone holds."""
    lines = []
    for slowdown in slowdowns:
        mine = [r for r in rows if r['slowdown'] == slowdown]
        lost = [r['start'] for r in mine if not held(r, limit)]
        line = (f'- compute x{slowdown:g}: {len(lost)} of {len(mine)} runs lost'
                + (f' (past {limit:g} rad or out of the domain)' if limit else '')
                + f"; longest step {max(r['longest'] for r in mine):.1f} periods")
        if against:
            kept = {tuple(r['start']) for r in reference
                    if r['slowdown'] == slowdown and held(r, limit)}
            worse = [start for start in lost if tuple(start) in kept]
            line += (f'; lost where `{against}` alone holds ({len(kept)} runs): {len(worse)}'
                     + (f" ({', '.join(str(start) for start in worse)})" if worse else ''))
        lines.append(line)
    return lines


def parser():
    p = argparse.ArgumentParser(prog='timed_rehearsal', description=__doc__.split('\n\n')[0])
    p.add_argument('--slowdown', type=float, nargs='+', default=[1.0, 1.5, 2.0])
    p.add_argument('--rate', type=float, default=100.0, help='plant samples a second')
    p.add_argument('--steps', type=int, default=800)
    p.add_argument('--law', default='koopman_nmpc')
    p.add_argument('--set', action='append', default=[], metavar='SECTION.SETTING=VALUE',
                   help="the law's settings and its sections' (observer, supervisor, "
                   'safety_filter), as deploy --set')
    p.add_argument('--against', metavar='LAW',
                   help='a verified law flown alone from the same starts at the same speeds '
                   '(its settings by --set too): the table then counts the runs the law lost '
                   'where this one holds')
    p.add_argument('--out', default=os.path.join('lab', 'results', 'timed_rehearsal'))
    p.add_argument('--page', default=PAGE)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.page:
        try:
            check_page(args.page, marker_name(args.out))
        except ValueError as error:
            print(f'timed_rehearsal: {error}', file=sys.stderr)
            return 2
    try:
        sections = parse_assignments(args.set)
    except ValueError as error:
        print(f'timed_rehearsal: {error}', file=sys.stderr)
        return 2
    law = make_controller(args.law, observer=sections.get('observer'),
                          supervisor=sections.get('supervisor'),
                          safety=sections.get('safety_filter'), **sections.get(args.law, {}))
    law.warm_up()
    rows, reference = [], []
    for slowdown in args.slowdown:
        for start in STARTS:
            rows.append(fly(start, slowdown, args.rate, args.steps, law))
            print(f'x{slowdown} {start}: {cell(rows[-1], True)}', flush=True)
    if args.against:
        verified = make_controller(args.against, **sections.get(args.against, {}))
        verified.warm_up()
        for slowdown in args.slowdown:
            for start in STARTS:
                reference.append({**fly(start, slowdown, args.rate, args.steps, verified),
                                  'law': args.against})
                print(f'{args.against} x{slowdown} {start}: {cell(reference[-1], True)}',
                      flush=True)
    header = ' | '.join(f'compute x{s:g}' for s in args.slowdown)
    settings = f" with {', '.join(args.set)}" if args.set else ' (the default)'
    command = shlex.join(['python', '-m', 'lab.timed_rehearsal',
                          *(sys.argv[1:] if argv is None else argv)])
    lines = [f'Measured by `{command}` ({stamp()}).', '',
             f'`{args.law}`{settings} at {args.rate:g} Hz, {args.steps} '
             'samples a run; each cell: settle time over the minimum time at the swing, '
             + ('the largest |theta| [rad], ' if args.set else '')
             + 'states dropped, the longest step after the first in periods, supervisor '
             'switches:', '', f'| start | {header} |',
             '|---|' + '---|' * len(args.slowdown)]
    for start in STARTS:
        cells = [cell(r, bool(args.set)) for s in args.slowdown for r in rows
                 if r['start'] == list(start) and r['slowdown'] == s]
        lines.append(f'| {list(start)} | ' + ' | '.join(cells) + ' |')
    bound = law.swing_bound()
    limit = bound + SWING_TOLERANCE if math.isfinite(bound) else None
    lines += [''] + summary(rows, reference, args.slowdown, args.against, limit)
    text = '\n'.join(lines) + '\n'
    publish(args.out, 'timed_rehearsal', rows + reference, text, args.page,
            marker=marker_name(args.out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
