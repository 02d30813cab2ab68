"""The README's first campaign, flown and its report shown: what a reviewer reads.

    python -m lab.campaign_example --out lab/results/campaign_example --page docs/campaign.md

flies `lab/campaigns/safety_filter.yaml` as the README's command does (its 40 dispersed
short-tether cases under a 0.4-rad swing bound, three laws paired) through the product's
campaign API, resumed where rows exist, and puts the report's tables and its two figures
(`figures/campaign_starts.png`, `figures/campaign_distributions.png`) into the page. The
worst cases and their replay commands stay in `<out>/report.md`: their paths are the run's.
"""

import argparse
import os
import re

from lab import campaigns
from lab.report import check_page, copy_figure, marker_name, stamp, write_into_page, \
    write_results

#: The spec the README's first campaign command flies (as the README names it).
SPEC = 'lab/campaigns/safety_filter.yaml'
#: The report's figures and the names they are copied to beside the page.
FIGURES = {'starts.png': 'figures/campaign_starts.png',
           'distributions.png': 'figures/campaign_distributions.png'}
#: The report's sections shown on the page (the worst cases' commands name <out>).
SHOWN = ('## Success per law', '## Paired: the laws on the same cases')


def parser():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--out', default='lab/results/campaign_example')
    p.add_argument('--page', default='', help='docs page with the markers named after --out')
    campaigns.add_engine_options(p)
    return p


def sections(report, names):
    """The report's sections titled `names` (each up to the next '## ' heading), images
    dropped: the page shows its own copies."""
    kept, keep = [], False
    for line in report.splitlines():
        if line.startswith('## '):
            keep = line in names
        if keep and not line.startswith('!['):
            kept.append(line.replace('## ', '**', 1) + '**' if line.startswith('## ')
                        else line)
    return re.sub(r'\n{3,}', '\n\n', '\n'.join(kept)).strip()


def main(argv=None):
    args = parser().parse_args(argv)
    if args.page:
        check_page(args.page, marker_name(args.out))
    from tsr_koopman_ctrl.campaign import load_spec
    campaigns.fly(load_spec(SPEC), args.out, args.workers, args.address)
    with open(os.path.join(args.out, 'report.md')) as f:       # (written by the campaign)
        text = f.read()
    heading = text.splitlines()[0].split(': ', 1)[1]       # '# Campaign: 40 runs x ...'
    command = ('python -m tsr_koopman_ctrl.commands.campaign --spec '
               f'{SPEC} --out {args.out}')
    body = [f'Flown by `python -m lab.campaign_example --out {args.out}` ({stamp()}), the '
            f'campaign of `{command}`: {heading}.', '', sections(text, SHOWN), '']

    def shown(names):
        return '\n'.join(body + [
            f'![the dispersed starts by outcome, one panel per law]({names["starts.png"]})', '',
            f'![settle, swing and compute per law]({names["distributions.png"]})'])
    own = shown({name: name for name in FIGURES})       # beside the report's own figures
    write_results(args.out, marker_name(args.out), {'report': text}, own)
    if args.page:
        for source, name in FIGURES.items():
            copy_figure(args.page, os.path.join(args.out, source), name)
        write_into_page(args.page, marker_name(args.out), shown(FIGURES))
    print(own)


if __name__ == '__main__':
    main()
