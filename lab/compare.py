"""The comparison: every law under each settings preset (untuned, tuned for the ratio, tuned for
the settle time) from the comparison and the held-out starts, scored against the minimum-time
frontier.
ROS-free (the DDS loop is step-identical).

    python -m lab.compare [--law ...] [--workers N | --address ADDR]
        [--out lab/results/comparison]

Every law runs offset-free (the default observer) with its settings from a preset: 'tuned' (the
laws' defaults, set by lab/tune.py --objective worst-ratio, the largest frontier ratio),
'tuned_settle' (config/tuned_settle.yaml: lab/tune.py on the mean settle time), 'untuned'
(config/untuned.yaml), or 'tuned_cross' (config/tuned_cross.yaml: the quadratic-cost laws
tuned for the ratio with the state weight's cross terms); a preset file shows the laws it
names. Per run: settle time
into the 1% zone, swing, the frontier at that swing from that start (evaluation/frontier.py,
computed by the project's own minimum-time solver) and the ratio, tension integral and peak,
the law's compute time per step (median, p99) and solver fallbacks. The runs are one campaign
(every law under every preset from every start) flown through the product's campaign API
(`tsr_koopman_ctrl.campaign`) into --out, resumed where --out holds its rows (a finished one is
read again, not flown: remove it to fly anew). Writes comparison.md, comparison.json and a
plot per start (every preset but 'untuned'), and the page's tables into --page between the
markers named after --out (`--page ""`: none).
"""

import argparse
import os
import sys

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl.control.registry import law_class, preset
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, run_figures
from tsr_koopman_ctrl.evaluation.figures import SWING_TOLERANCE
from tsr_koopman_ctrl.evaluation.plots import plot_deployments, plot_ratios
from tsr_koopman_ctrl import arguments
from lab.campaigns import add_engine_options, fly
from lab.report import check_page, marker_name, stamp, write_into_page, write_results


#: What a comparison's campaign rows carry beyond their own: the compute's tail, the solver's
#: fallbacks, and the loop (the plots'; `run_figures` of it gives the rest of the table).
FIGURES = ('compute_p99_ms', 'fallbacks', 'states', 'tensions')


def campaign(laws, presets, steps, theta_max=None):
    """(the campaign of every law under every preset from every start, {law label: (law,
    preset label, plotted)}). `theta_max`: a hard swing bound given to the laws that take one
    (the others are left out)."""
    from tsr_koopman_ctrl.campaign import Campaign
    if theta_max is not None:
        bounded = [law for law in CONTROLLERS
                   if 'theta_max' in law_class(law).Settings.__dataclass_fields__]
        if not set(laws) & set(bounded):
            raise ValueError(f'--theta-max: none of {list(laws)} takes a swing bound (those '
                             f'that do: {sorted(bounded)})')
        left_out = [law for law in laws if law not in bounded]
        if left_out:
            print(f'--theta-max: {", ".join(left_out)} take no swing bound: left out', flush=True)
        laws = [law for law in laws if law in bounded]
    # Every preset read and checked before the first run, which takes minutes.
    preset_values = {name: {} if name == 'tuned' else preset(name)
                     for name in dict.fromkeys(presets)}    # each preset once, in order
    for name, values in preset_values.items():
        if name != 'tuned' and not set(values) & set(laws):
            raise ValueError(f'--presets {name}: sets none of the laws compared '
                             f'({list(laws)}), only {sorted(values)}')
    entries, meaning = [], {}
    for index, (name, values) in enumerate(preset_values.items()):
        for law in laws:
            if name != 'tuned' and law not in values:
                continue    # a preset file shows the laws it names, not defaults under its name
            settings = dict(values.get(law, {}))
            label = name
            if theta_max is not None:
                settings['theta_max'] = theta_max
                label += f', |theta| <= {theta_max:g}'
            key = f'{law}_preset_{index}'       # a campaign label: a name, one per (law, preset)
            entries.append({'law': law, 'label': key, 'settings': {law: settings}})
            # Untuned runs stay out of the plots: ten curves per panel are already many.
            meaning[key] = (law, label, os.path.splitext(os.path.basename(name))[0] != 'untuned')
    spec = {'steps': steps, 'start': ['comparison', 'held_out'], 'laws': entries,
            'figures': list(FIGURES)}
    return Campaign.parse(spec, where='compare'), meaning


def compare(laws, presets, steps, theta_max=None, out=None, workers=None, address=None):
    """Rows and loops of every law under every preset from every start, flown as one campaign
    into `out` (resumed if begun there)."""
    flown, meaning = campaign(laws, presets, steps, theta_max)
    found = fly(flown, out, workers, address)
    order = [entry.label for entry in flown.laws]
    comparison = len(COMPARISON_STARTS)
    rows, loops = [], {}
    for record in sorted(found.to_dict('records'),
                         key=lambda r: (order.index(r['law']), int(r['run']))):
        law, label, plotted = meaning[record['law']]
        start = list(flown.start_list[flown.position(int(record['run']))[0]])
        states = np.array([list(x) for x in record['states']], dtype=float)
        tensions = np.asarray(record['tensions'], dtype=float)
        tau = np.arange(len(states)) * dynamics.PAPER_STEP
        row = run_figures(tau, states, tensions, start=start, halted=bool(record['halted'])) \
            if len(states) else {'settle_tau': None, 'swing': float('nan'), 'halted': True,
                                 'frontier_tau': None, 'frontier_ratio': None,
                                 'tension_integral': 0.0, 'tension_max': 0.0}
        row.update(compute_median_us=float(record['compute_median_ms']) * 1e3,
                   compute_p99_us=float(record['compute_p99_ms']) * 1e3,
                   fallbacks=int(record['fallbacks']), law=law, preset=label, start=start,
                   starts='comparison' if flown.position(int(record['run']))[0] < comparison
                   else 'held-out')
        rows.append(row)
        if plotted:
            loops.setdefault(tuple(start), {})[f'{law} ({label})'] = (tau, states, tensions)
        settle, ratio = row['settle_tau'], row['frontier_ratio']
        print(f'{law} ({label}) from {start}: settle '
              f"{'-' if settle is None else f'{settle:.2f}'}, ratio "
              f"{'-' if ratio is None else f'{ratio:.3f}'}", flush=True)
    return rows, loops


def fmt(value, digits=2):
    return '-' if value is None else f'{value:.{digits}f}'


def cell(text):
    """A table cell: a '|' in it (the swing-bound label) escaped so it stays one column."""
    return str(text).replace('|', '\\|')


def markdown(rows):
    lines = ['| law | settings | starts | x0 | settle tau | swing [rad] | frontier tau | ratio | '
             'integral u dtau | max u | compute median / p99 [us] | fallbacks |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        settle = fmt(r['settle_tau']) if r['settle_tau'] is not None else (
            'left the domain' if r['halted'] else 'not reached')
        lines.append(f"| {r['law']} | {cell(r['preset'])} | {r['starts']} | {r['start']} | "
                     f"{settle} | {r['swing']:.3f} | {fmt(r['frontier_tau'])} | "
                     f"{fmt(r['frontier_ratio'])} | {r['tension_integral']:.2f} | "
                     f"{r['tension_max']:.2f} | {r['compute_median_us']:.0f} / "
                     f"{r['compute_p99_us']:.0f} | {r['fallbacks']} |")
    lines += ['', '| law | settings | settled (comparison + held-out) | frontier ratio, '
              'comparison starts | frontier ratio, held-out starts |', '|---|---|---|---|---|']
    keys = sorted({(r['law'], r['preset']) for r in rows}, key=lambda k: (k[1], k[0]))
    for law, name in keys:
        mine = [r for r in rows if (r['law'], r['preset']) == (law, name)]
        settled = sum(r['settle_tau'] is not None for r in mine)

        def span(kind):
            ratios = [r['frontier_ratio'] for r in mine if r['starts'] == kind
                      and r['frontier_ratio'] is not None]
            return f'{min(ratios):.2f}..{max(ratios):.2f}' if ratios else '-'
        lines.append(f'| {law} | {cell(name)} | {settled}/{len(mine)} | {span("comparison")} | '
                     f'{span("held-out")} |')
    return '\n'.join(lines) + '\n'


def page_tables(rows, theta_max=None):
    """The page's view of a comparison: settle tau / swing / frontier ratio per start and law
    (the 'tuned' preset, else the first), then one row per law and preset; with a swing bound,
    where each law held it."""
    presets = list(dict.fromkeys(r['preset'] for r in rows))
    shown = next((p for p in presets if p.split(',')[0] == 'tuned'), presets[0])

    def mean(values):
        values = [v for v in values if v is not None]
        return float(np.mean(values)) if values else None

    def of(law, name):
        return [r for r in rows if (r['law'], r['preset']) == (law, name)]
    laws = sorted(dict.fromkeys(r['law'] for r in rows),
                  key=lambda law: mean(r['frontier_ratio'] for r in of(law, shown)) or np.inf)
    lines = [f"{stamp()}, {len(rows)} runs. Settle tau / swing [rad] / **frontier ratio**, "
             f'settings `{shown}`:', '',
             '| x0 | ' + ' | '.join(f'`{law}`' for law in laws if of(law, shown)) + ' |',
             '|---' * (1 + sum(bool(of(law, shown)) for law in laws)) + '|']
    for start in dict.fromkeys(tuple(r['start']) for r in rows):
        mine = {r['law']: r for r in rows if r['preset'] == shown and tuple(r['start']) == start}
        kind = next(iter(mine.values()))['starts']
        cells = []
        for law in laws:
            if law in mine:
                r = mine[law]
                settle = fmt(r['settle_tau']) if r['settle_tau'] is not None else (
                    'tumbled' if r['halted'] else 'not settled')
                cells.append(f"{settle} / {r['swing']:.2f} / **{fmt(r['frontier_ratio'])}**")
        label = f'{list(start)}' + (' (held-out)' if kind == 'held-out' else '')
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    lines += ['', 'Per law and settings (compute: the median of the runs\' median step on this '
              'machine):', '',
              '| law | settings | settles | mean settle tau, comparison / held-out | '
              'frontier ratio | peak tension | compute median [ms] | fallbacks |',
              '|---|---|---|---|---|---|---|---|']
    for name in presets:
        for law in laws:
            mine = of(law, name)
            if not mine:
                continue
            ratios = [r['frontier_ratio'] for r in mine if r['frontier_ratio'] is not None]
            span = f'{min(ratios):.2f}..{max(ratios):.2f}' if ratios else '-'
            means = ' / '.join(fmt(mean(r['settle_tau'] for r in mine if r['starts'] == kind))
                               for kind in ('comparison', 'held-out'))
            settled = sum(r['settle_tau'] is not None for r in mine)
            compute = np.median([r['compute_median_us'] for r in mine]) / 1000
            lines.append(f'| `{law}` | {cell(name)} | {settled}/{len(mine)} | {means} | {span} | '
                         f"{max(r['tension_max'] for r in mine):.2f} | {compute:.2f} | "
                         f"{sum(r['fallbacks'] for r in mine)} |")
    if theta_max is not None:
        bound = theta_max + SWING_TOLERANCE
        lines += ['', f'Where each law held the bound (swing <= {bound:g} rad on the plant):', '',
                  '| law | settings | held | swing where held | frontier ratio where held | '
                  'where it did not: start, swing, outcome |', '|---|---|---|---|---|---|']
        for name in presets:
            for law in laws:
                mine = of(law, name)
                if not mine:
                    continue
                held = [r for r in mine if r['swing'] <= bound]
                lost = [r for r in mine if r['swing'] > bound]
                swings = [r['swing'] for r in held]
                swings = f'{min(swings):.3f}..{max(swings):.3f}' if held else '-'
                ratios = [r['frontier_ratio'] for r in held if r['frontier_ratio'] is not None]
                span = f'{min(ratios):.2f}..{max(ratios):.2f}' if ratios else '-'
                where = '; '.join(
                    f"{tuple(r['start'])}: {r['swing']:.2f}, "
                    + (f"settled {r['settle_tau']:.2f}" if r['settle_tau'] is not None else
                       'tumbled' if r['halted'] else 'not settled') for r in lost) or '-'
                lines.append(f'| `{law}` | {cell(name)} | {len(held)}/{len(mine)} | {swings} | '
                             f'{span} | {where} |')
    return '\n'.join(lines) + '\n'


def parser():
    p = argparse.ArgumentParser(prog='compare', description=__doc__.split('\n\n')[0])
    p.add_argument('--law', nargs='+', default=sorted(CONTROLLERS), choices=sorted(CONTROLLERS),
                   help='default: every law')
    p.add_argument('--presets', nargs='+', default=['untuned', 'tuned', 'tuned_settle'],
                   help="settings presets: 'tuned' (the laws' defaults), or a parameter file "
                   "by path or by name under config/ ('untuned', 'tuned_settle', "
                   "'tuned_cross'); a file shows the laws it names")
    p.add_argument('--steps', type=arguments.STEPS, default=2000)
    p.add_argument('--theta-max', type=arguments.number(above=0), metavar='RAD',
                   help='a swing bound for the laws that take one (koopman_mpc: soft; '
                   'physics_nmpc, koopman_nmpc: exact penalty); the others are left out')
    add_engine_options(p)
    p.add_argument('--out', default=os.path.join('out', 'comparison'), type=arguments.output_dir)
    p.add_argument('--page', default='', help='a docs page to write the tables into, between '
                   'the markers named after --out (docs/comparison.md has them)')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    try:
        if args.page:
            check_page(args.page, marker_name(args.out))
        rows, loops = compare(args.law, args.presets, args.steps, args.theta_max, args.out,
                              args.workers, args.address)
    except ValueError as error:
        print(f'compare: {error}', file=sys.stderr)
        return 2
    text = markdown(rows)
    write_results(args.out, 'comparison', rows, text)
    if args.page:
        write_into_page(args.page, marker_name(args.out), page_tables(rows, args.theta_max))
    for index, (start, runs) in enumerate(loops.items()):
        plot_deployments(runs, os.path.join(args.out, f'x0_{index}.png'),
                         title=f'TSR deployment from x0 = {list(start)}')
    shown = {label for runs in loops.values() for label in runs}    # the plots' runs (no untuned)
    plot_ratios([r for r in rows if f"{r['law']} ({r['preset']})" in shown],
                os.path.join(args.out, 'ratios.png'))
    print(text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
