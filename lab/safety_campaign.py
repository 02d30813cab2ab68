"""The predictive safety filter signed off by Monte Carlo: three campaign specs and their page.

    python -m lab.safety_campaign --out lab/results/safety_campaign --page docs/supervisor.md

flies `lab/campaigns/safety_filter.yaml` (dispersed short-tether starts, actuators and sensor
noise, a 0.4-rad swing bound: the filtered learned law, the same law under its supervisor
alone, the verified law alone), `lab/campaigns/safety_filter_nominal.yaml` (the nine
comparison starts, nominal plant, no swing bound: filtered and supervised) and
`lab/campaigns/safety_filter_domain.yaml` (the whole domain, dense at the short tether,
dispersed plants, no swing bound: filtered and the verified law alone) through the
product's campaign API (`tsr_koopman_ctrl.campaign`, resumed where rows exist), then writes
the figures the safety issue asks for: cases lost where the verified law holds, the settle time
against the verified law's where both hold, how often and how much the filter corrects.
"""

import argparse
import os

from lab.report import check_page, marker_name, publish, stamp

SPECS = {'dispersed': 'lab/campaigns/safety_filter.yaml',
         'nominal': 'lab/campaigns/safety_filter_nominal.yaml',
         'domain': 'lab/campaigns/safety_filter_domain.yaml'}


def parser():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--out', default='lab/results/safety_campaign')
    p.add_argument('--page', default='', help='docs page with the markers named after --out')
    p.add_argument('--runs', type=int,
                   help='cases of each part with dispersed starts (default: the spec\'s)')
    p.add_argument('--workers', type=int, help='local Dask workers (default: one per core)')
    p.add_argument('--address', help='a Dask scheduler to run on instead')
    return p


def fly(out, runs=None, workers=None, address=None):
    """{part: rows} of the campaigns, each under <out>/<part>, resumed if begun."""
    from tsr_koopman_ctrl.campaign import load_spec, run_campaign
    rows = {}
    for part in SPECS:
        campaign = load_spec(SPECS[part])
        if runs and campaign.start_box:
            campaign = load_spec(SPECS[part], runs=runs)
        directory = os.path.join(out, part)
        resume = os.path.exists(os.path.join(directory, 'spec.yaml'))
        rows[part] = run_campaign(campaign, directory, workers=workers, address=address,
                                  resume=resume)
    return rows


def by_law(rows):
    """{label: rows indexed by run}."""
    return {label: group.set_index('run').sort_index() for label, group in rows.groupby('law')}


def held(group, limit=None):
    ok = ~group['halted'].astype(bool) & (group['error'] == '')
    return ok if limit is None else ok & (group['swing'] <= limit)


def figures(rows, limit=None, reference='physics'):
    """The filtered law against `reference` on the same cases (module docstring)."""
    from tsr_koopman_ctrl.campaign.report import clopper_pearson
    laws = by_law(rows)
    filtered, other = laws['filtered'], laws[reference]
    ok_f, ok_r = held(filtered, limit), held(other, limit)
    lost = sorted(int(run) for run in filtered.index[ok_r & ~ok_f])
    both = ok_f & ok_r & filtered['settle_tau'].notna() & other['settle_tau'].notna()
    ratio = filtered['settle_tau'][both] / other['settle_tau'][both]
    lost_by = {label: sorted(int(run) for run in group.index[ok_r & ~held(group, limit)])
               for label, group in laws.items() if label not in ('filtered', reference)}
    worst = ratio.sort_values(ascending=False)
    result = {'cases': len(filtered), 'reference': reference, 'lost_where_reference_holds': lost,
              'lost_by': lost_by, 'reference_held': int(ok_r.sum()),
              'settle_ratio_over_1.05': [int(run) for run in worst.index[worst > 1.05]],
              'held': {label: int(held(group, limit).sum()) for label, group in laws.items()},
              'held_interval': {label: clopper_pearson(int(held(group, limit).sum()),
                                                       len(group))
                                for label, group in laws.items()},
              'settle_ratio_median': float(ratio.median()) if len(ratio) else None,
              'settle_ratio_max': float(ratio.max()) if len(ratio) else None,
              'both_settled': int(both.sum()),
              'corrections_median': float(filtered['corrections'].median()),
              'corrections_max': int(filtered['corrections'].max()),
              'compute_median_ms': {label: float(group['compute_median_ms'].median())
                                    for label, group in laws.items()}}
    return result


def table(part, result, steps):
    lines = [f"**{part}** ({result['cases']} cases, {steps} steps each; against "
             f"`{result['reference']}` on the same cases)", '',
             '| law | cases held | 95% interval | median compute [ms] |', '|---|---|---|---|']
    for label, count in result['held'].items():
        low, high = result['held_interval'][label]
        lines.append(f"| {label} | {count} of {result['cases']} | [{low:.3f}, {high:.3f}] | "
                     f"{result['compute_median_ms'][label]:.2f} |")
    lost = result['lost_where_reference_holds']
    ratio = ('-' if result['settle_ratio_median'] is None else
             f"median {result['settle_ratio_median']:.3f}, largest "
             f"{result['settle_ratio_max']:.3f} ({result['both_settled']} cases)")

    def runs(numbers, shown=10):
        more = f', ... {len(numbers) - shown} more' if len(numbers) > shown else ''
        listed = f" (runs {', '.join(map(str, numbers[:shown]))}{more})" if numbers else ''
        return f'{len(numbers)}{listed}'
    over = result['settle_ratio_over_1.05']
    lines += ['', f"- lost by the filtered law where `{result['reference']}` holds "
              f"({result['reference_held']} cases): {runs(lost)}"]
    lines += [f"- lost by `{label}` there: {len(numbers)}"
              for label, numbers in result['lost_by'].items()]
    lines += [f"- settle time past 1.05x `{result['reference']}`'s: {runs(over)}",
              f"- settle time, filtered / `{result['reference']}` where both settle: {ratio}",
              f"- steps corrected by the filter per run: median {result['corrections_median']:.0f}"
              f" of {steps}, largest {result['corrections_max']}"]
    return '\n'.join(lines)


def main(argv=None):
    args = parser().parse_args(argv)
    if args.page:
        check_page(args.page, marker_name(args.out))
    rows = fly(args.out, args.runs, args.workers, args.address)
    from tsr_koopman_ctrl.campaign import load_spec
    dispersed, nominal, domain = (load_spec(SPECS[part]) for part in SPECS)
    results = {'dispersed': figures(rows['dispersed'], dispersed.swing_limit),
               'nominal': figures(rows['nominal'], None, reference='supervised'),
               'domain': figures(rows['domain'], domain.swing_limit)}
    command = ' '.join(['python -m lab.safety_campaign']
                       + ([f'--runs {args.runs}'] if args.runs else [])
                       + [f'--out {args.out}'] + ([f'--page {args.page}'] if args.page else []))
    text = '\n\n'.join([
        f'Measured by `{command}` ({stamp()}; the rows: `<out>/<part>/runs.parquet`, the '
        'campaigns\' own reports beside them):',
        table('Dispersed, swing bound 0.4 rad (`lab/campaigns/safety_filter.yaml`)',
              results['dispersed'], dispersed.steps),
        table('Nominal plant, no swing bound, the nine comparison starts '
              '(`lab/campaigns/safety_filter_nominal.yaml`)', results['nominal'],
              nominal.steps),
        table('The whole domain, dense at the short tether, no swing bound '
              '(`lab/campaigns/safety_filter_domain.yaml`)', results['domain'],
              domain.steps)])
    publish(args.out, marker_name(args.out), results, text, args.page)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
