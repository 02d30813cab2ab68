"""Offset-free control against actuator error, lag and sensor noise: the settle-time grid.

    python -m lab.robustness [--law koopman_mpc linear_lqr] [--steps K] [--runs N]
        [--workers N | --address ADDR] [--out DIR] [--page PAGE]

Flies lab/campaigns/robustness.yaml (each law bare and offset-free, every start on every plant
case: nominal, a lagging actuator too weak or too strong, with and without sensor noise)
through the product's campaign API (`tsr_koopman_ctrl.campaign`, resumed where --out holds its
rows), then renders from <out>/runs.parquet the settle time into the 1% zone (judged on the
true state) and its ratio to the same law's on the nominal plant from the same start.
`--law` flies other laws (each bare and offset-free), `--steps` and `--runs` a shorter or a
partial grid. With --page, the page's tables go into it between the markers named after --out.
"""

import argparse
import math
import os
import sys

from tsr_koopman_ctrl import arguments
from tsr_koopman_ctrl.control import CONTROLLERS
from lab.campaigns import add_engine_options, fly, spec_path
from lab.report import check_page, marker_name, publish, stamp, write_into_page

SPEC = spec_path('robustness.yaml')
#: The case every other is measured against.
NOMINAL = 'nominal'


def law_pair(law):
    """A law's two entries in the grid: bare (labelled <law>_bare) and offset-free (<law>)."""
    return [{'law': law, 'label': f'{law}_bare', 'set': ['observer.disturbance=none']},
            {'law': law, 'label': law}]


def load(laws=None, steps=None, runs=None):
    """The grid's campaign: the spec's, with other laws (each bare and offset-free), steps or
    runs if given."""
    from tsr_koopman_ctrl.campaign import load_spec
    entries = None if laws is None else [entry for law in laws for entry in law_pair(law)]
    return load_spec(SPEC, laws=entries, steps=steps, runs=runs)


def control(entry):
    """'bare' for a law flown with its observer off, else 'offset-free'."""
    bare = entry.settings.get('observer', {}).get('disturbance') == 'none'
    return 'bare' if bare else 'offset-free'


def starts(campaign):
    return [list(x0) for x0 in campaign.start_list]


def grid(campaign, rows):
    """Per law label and plant case (in the spec's order, the cases flown): the starts' settle
    tau, final l - 1 and ratio to the same label's nominal settle from the same start."""
    def value(number):
        return None if number is None or math.isnan(number) else float(number)
    flown = {}
    for row in rows.to_dict('records'):
        start, _ = campaign.position(int(row['run']))
        flown[row['law'], row['case'], start] = (value(row['settle_tau']),
                                                 value(row['final_length_offset']))
    table = []
    for entry in campaign.laws:
        for case in campaign.cases:
            mine = [flown.get((entry.label, case.label, i)) for i in range(len(starts(campaign)))]
            if not any(mine):
                continue
            results = []
            for i, (x0, result) in enumerate(zip(starts(campaign), mine)):
                if result is None:
                    continue
                tau, offset = result
                nominal = (flown.get((entry.label, NOMINAL, i)) or (None, None))[0]
                results.append({'x0': x0, 'settle_tau': tau, 'final_length_offset': offset,
                                'ratio': None if tau is None or nominal is None
                                else tau / nominal})
            table.append({'law': entry.law, 'control': control(entry), 'case': case.label,
                          'starts': results})
    return table


def markdown(table, campaign):
    lines = ['Settle tau into the 1% zone (true state) per start '
             f'({", ".join(str(x) for x in starts(campaign))}); in brackets the ratio to the '
             'same law on the nominal plant; "-" did not settle (final l - 1 given).', '',
             '| law | control | plant | settled | worst ratio | per start |',
             '|---|---|---|---|---|---|']
    for r in table:
        settled = [s for s in r['starts'] if s['settle_tau'] is not None]
        ratios = [s['ratio'] for s in settled if s['ratio'] is not None]
        cells = ', '.join(f"{s['settle_tau']:.2f} ({s['ratio']:.2f})" if s['settle_tau']
                          is not None and s['ratio'] is not None
                          else f"{s['settle_tau']:.2f}" if s['settle_tau'] is not None
                          else f"- ({s['final_length_offset']:+.3f})" for s in r['starts'])
        worst = f'{max(ratios):.2f}' if ratios else '-'
        lines.append(f"| {r['law']} | {r['control']} | {r['case']} | "
                     f"{len(settled)}/{len(r['starts'])} | {worst} | {cells} |")
    return '\n'.join(lines) + '\n'


def actuator(campaign, label):
    """(gain, lag) of a plant case (None where it sets none)."""
    case = next(c for c in campaign.cases if c.label == label)
    return case.fixed.get('actuator_gain'), case.fixed.get('actuator_lag')


def page_tables(table, campaign):
    """The page's view: per law and control, the nominal settle times and how the disturbed
    cases went; then the first law's offset-free ratio per actuator gain and start (no
    noise)."""
    lines = [f'{stamp()}. Settle tau into the 1% zone, judged on the true state; "within '
             '1.2x": of its own nominal settle time from the same start.', '',
             '| law | nominal plant, settle tau per start | disturbed: settled | '
             'disturbed: within 1.2x its nominal | worst ratio to its nominal |',
             '|---|---|---|---|---|']
    for law, kind in dict.fromkeys((r['law'], r['control']) for r in table):
        mine = [r for r in table if (r['law'], r['control']) == (law, kind)]
        nominal = next((r for r in mine if r['case'] == NOMINAL), {'starts': []})['starts']
        disturbed = [s for r in mine if r['case'] != NOMINAL for s in r['starts']]
        settled = [s for s in disturbed if s['settle_tau'] is not None]
        ratios = [s['ratio'] for s in settled if s['ratio'] is not None]
        label = 'offset-free (default)' if kind == 'offset-free' else kind
        times = ', '.join('-' if s['settle_tau'] is None else f"{s['settle_tau']:.2f}"
                          for s in nominal)
        lines.append(f'| `{law}`, {label} | {times} | {len(settled)} / {len(disturbed)} | '
                     f'{sum(q <= 1.2 for q in ratios)} | '
                     f"{f'{max(ratios):.2f}' if ratios else '-'} |")
    first = table[0]['law']
    noiseless = [r for r in table if (r['law'], r['control']) == (first, 'offset-free')
                 and r['case'] != NOMINAL
                 and 'sensor_noise_std' not in next(c for c in campaign.cases
                                                    if c.label == r['case']).fixed]
    lags = sorted({actuator(campaign, r['case'])[1] for r in noiseless} - {None})
    lag = ', '.join(f'{v:g}' for v in lags)
    lines += ['', f'The offset-free `{first}`, ratio to its nominal settle time per start (no '
              'sensor noise; "-": not settled):', '',
              f'| actuator gain (lag {lag} tau) | '
              + ' | '.join(str(tuple(x)) for x in starts(campaign)) + ' |',
              '|---' * (len(starts(campaign)) + 1) + '|']
    for r in noiseless:
        gain = actuator(campaign, r['case'])[0]
        lines.append(f'| {gain:g} | ' + ' | '.join(
            '-' if s['ratio'] is None else f"{s['ratio']:.2f}" for s in r['starts']) + ' |')
    return '\n'.join(lines) + '\n'


def parser():
    p = argparse.ArgumentParser(prog='robustness', description=__doc__.split('\n\n')[0])
    p.add_argument('--law', nargs='+', choices=sorted(CONTROLLERS),
                   help="the laws, each bare and offset-free (default: the spec's)")
    p.add_argument('--steps', type=arguments.STEPS, help="steps per run (default: the spec's)")
    p.add_argument('--runs', type=arguments.integer(1), help='the first N runs of the grid '
                   '(run n flies start n mod S and case n // S; default: all)')
    add_engine_options(p)
    p.add_argument('--out', default=os.path.join('out', 'robustness'), type=arguments.output_dir)
    p.add_argument('--page', default='', help='a docs page to write the tables into, between '
                   'the markers named after --out (docs/robustness.md has them)')
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    try:
        if args.page:
            check_page(args.page, marker_name(args.out))
        campaign = load(args.law, args.steps, args.runs)
        rows = fly(campaign, args.out, args.workers, args.address)
    except ValueError as error:
        print(f'robustness: {error}', file=sys.stderr)
        return 2
    table = grid(campaign, rows)
    publish(args.out, 'robustness', table, markdown(table, campaign))
    if args.page:
        write_into_page(args.page, marker_name(args.out), page_tables(table, campaign))
    return 0


if __name__ == '__main__':
    sys.exit(main())
