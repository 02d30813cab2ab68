"""A campaign's report, from its directory alone (spec.yaml and the rows): <out>/report.md and
its figures.

Success: the run did not halt (leave the domain or tumble), flew without error, and its swing
stayed within the spec's swing limit if it sets one. Each law's success rate comes with its
95% Clopper-Pearson interval (exact, from the beta distribution); the laws are compared on the
same cases (paired); the worst cases come with the commands that replay them.
"""

import math
import os
import shlex

from tsr_koopman_ctrl.campaign import rows as stored
from tsr_koopman_ctrl.campaign.spec import Campaign

CONFIDENCE = 0.95
WORST_CASES = 5
#: The command that replays a run ROS-free, in this checkout.
REPLAY = 'python -m tsr_koopman_ctrl.commands.campaign replay'


def clopper_pearson(successes, trials, confidence=CONFIDENCE):
    """(low, high) of the exact two-sided interval of a success probability: 0 of n gives
    (0, 1 - ((1 - confidence) / 2) ** (1 / n))."""
    from scipy.stats import beta
    if not 0 <= successes <= trials or trials < 1:
        raise ValueError(f'clopper_pearson: need 0 <= successes <= trials, trials >= 1, got '
                         f'{successes} of {trials}')
    alpha = 1.0 - confidence
    low = 0.0 if successes == 0 else float(beta.ppf(alpha / 2, successes,
                                                    trials - successes + 1))
    high = 1.0 if successes == trials else float(beta.ppf(1 - alpha / 2, successes + 1,
                                                          trials - successes))
    return low, high


def successes(rows, swing_limit=None):
    """Which rows succeeded (a boolean Series)."""
    ok = ~rows['halted'].astype(bool) & (rows['error'] == '')
    if swing_limit is not None:
        ok &= rows['swing'] <= swing_limit
    return ok


def outcome(row, swing_limit=None):
    if row['error']:
        return 'error'
    if row['halted']:
        return 'halted'
    if swing_limit is not None and row['swing'] > swing_limit:
        return 'over swing limit'
    return 'settled' if not math.isnan(row['settle_tau']) else 'not settled'


def _severity(rows, swing_limit):
    """A sort key, worst first: failed, then not settled, then the longest settle, the widest
    swing."""
    failed = ~successes(rows, swing_limit)
    settle = rows['settle_tau'].fillna(math.inf)
    return (-failed.astype(int), -settle, -rows['swing'].fillna(math.inf))


def replay_commands(out, campaign, row):
    """(ROS-free replay, replay over DDS with a bag) of one row: the lines a reviewer runs.
    A plant other than a named variant is written to <out>/plants/run_<n>.yaml for deploy."""
    run, label = int(row['run']), row['law']
    local = f'{REPLAY} {shlex.quote(out)} --run {run} --law {label}'
    entry = campaign.law(label)
    case = campaign.case(run)
    words = ['ros2', 'run', 'tsr_koopman_ctrl', 'deploy', '--law', entry.law, '--steps',
             str(campaign.steps), '--x0', *(repr(float(v)) for v in case.x0)]
    for section, values in entry.settings.items():
        for name, value in values.items():
            text = ','.join(repr(v) for v in value) if isinstance(value, tuple) else (
                str(value).lower() if isinstance(value, bool) else str(value))
            words += ['--set', f'{section}.{name}={text}']
    if set(case.plant) - {'seed'}:       # the nominal plant needs no file (nor a seed)
        path = os.path.join(out, 'plants', f'run_{run}.yaml')
        write_plant_file(path, case.plant)
        words += ['--plant', path]
    return local, ' '.join(shlex.quote(w) for w in words)


def write_plant_file(path, plant):
    """A plant file (`deploy --plant FILE`): the case's plant parameters, its noise seed
    included."""
    import yaml
    os.makedirs(os.path.dirname(path), exist_ok=True)
    plain = {k: (list(v) if isinstance(v, tuple) else v) for k, v in plant.items()}
    with open(path, 'w') as stream:
        yaml.safe_dump({'/**': {'ros__parameters': plain}}, stream, sort_keys=True)


def _table(header, lines):
    return '\n'.join(['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header),
                      *('| ' + ' | '.join(str(c) for c in line) + ' |' for line in lines)])


def _figure(value, digits=3):
    return '-' if value is None or (isinstance(value, float) and math.isnan(value)) else (
        f'{value:.{digits}g}')


def write_report(out):
    """<out>/report.md and its figures (distributions.png, starts.png); returns the text."""
    campaign = Campaign.parse(stored.read_spec(out), where=os.path.join(out, stored.SPEC_FILE))
    rows = stored.read_rows(out)
    limit = campaign.swing_limit
    labels = [e.label for e in campaign.laws]
    cases = f' ({len(campaign.cases)} plant cases)' if campaign.cases else ''
    lines = [f'# Campaign: {campaign.runs} runs{cases} x {len(labels)} laws, {campaign.steps} '
             f'steps, seed {campaign.seed}', '',
             f'{len(rows)} of {len(campaign.pairs())} runs flown. Success: not halted (left '
             'the domain or tumbled)' + (f' and swing <= {limit:g} rad' if limit else '') +
             f'; bounds: {CONFIDENCE:.0%} Clopper-Pearson.', '']
    if not len(rows):
        text = '\n'.join(lines) + '\n'
        with open(os.path.join(out, 'report.md'), 'w') as f:
            f.write(text)
        return text
    ok = successes(rows, limit)
    table = []
    for label in labels:
        mine = rows['law'] == label
        n, k = int(mine.sum()), int((ok & mine).sum())
        if not n:
            continue
        low, high = clopper_pearson(k, n)
        law = rows[mine]
        table.append([f'`{label}`', f'{k} / {n}', f'{k / n:.1%}', f'[{low:.1%}, {high:.1%}]',
                      _figure(law['settle_tau'].median()), _figure(law['swing'].max()),
                      _figure(law['compute_median_ms'].median()),
                      int(law['corrections'].sum()), int(law['switches'].sum())])
    lines += ['## Success per law', '', _table(
        ['law', 'successes', 'rate', '95% bounds', 'median settle tau', 'max swing [rad]',
         'compute median [ms]', 'corrections', 'switches'], table), '']
    if campaign.cases:
        lines += _per_case(rows, labels, [c.label for c in campaign.cases], ok)
    _plots(out, rows, labels, ok, limit)
    lines += ['![settle, swing and compute per law](distributions.png)', '',
              '![the dispersed starts, by outcome](starts.png)', '']
    lines += _paired(rows, labels, ok)
    lines += ['## Worst cases', '',
              'Each with the command that replays it ROS-free (the same figures as its row) '
              'and the one that flies it over DDS with a bag (lockstep; a dispersed plant is '
              'passed as a plant file under plants/).', '']
    for label in labels:
        law = rows[rows['law'] == label]
        worst = law.iloc[sorted(range(len(law)), key=lambda i: tuple(
            key.iloc[i] for key in _severity(law, limit)))[:WORST_CASES]]
        lines += [f'### `{label}`', '']
        for _, row in worst.iterrows():
            local, dds = replay_commands(out, campaign, row)
            start = ', '.join(f'{row[f"x0_{i}"]:.4g}' for i in range(4))
            dispersed = ''.join(f', {name} {row[name]:.4g}'
                                for name in campaign.dispersed_names()
                                if not math.isnan(row[name]))
            case = f', case {row["case"]}' if campaign.cases else ''
            lines += [f'- run {int(row["run"])}{case}: {outcome(row, limit)}, settle '
                      f'{_figure(row["settle_tau"])}, swing {_figure(row["swing"])}; start '
                      f'[{start}]{dispersed}' + (f'; {row["error"]}' if row['error'] else ''),
                      f'  - `{local}`', f'  - `{dds}`']
        lines.append('')
    text = '\n'.join(lines)
    with open(os.path.join(out, 'report.md'), 'w') as f:
        f.write(text)
    return text


def _per_case(rows, labels, cases, ok):
    """Each law's successes on each plant case."""
    table = []
    for label in labels:
        for case in cases:
            mine = (rows['law'] == label) & (rows['case'] == case)
            n, k = int(mine.sum()), int((ok & mine).sum())
            if not n:
                continue
            low, high = clopper_pearson(k, n)
            table.append([f'`{label}`', case, f'{k} / {n}', f'[{low:.1%}, {high:.1%}]',
                          _figure(rows.loc[mine, 'settle_tau'].median()),
                          _figure(rows.loc[mine, 'swing'].max())])
    return ['## Success per law and plant case', '', _table(
        ['law', 'case', 'successes', '95% bounds', 'median settle tau', 'max swing [rad]'],
        table), '']


def _paired(rows, labels, ok):
    """The laws compared two by two on the same runs."""
    if len(labels) < 2:
        return []
    table = []
    by = rows.assign(ok=ok).set_index(['run', 'law'])
    for i, a in enumerate(labels):
        for b in labels[i + 1:]:
            runs = sorted(set(rows.loc[rows['law'] == a, 'run'])
                          & set(rows.loc[rows['law'] == b, 'run']))
            if not runs:
                continue
            first, second = by.xs(a, level='law').loc[runs], by.xs(b, level='law').loc[runs]
            ratio = (first['settle_tau'] / second['settle_tau']).dropna()
            only_a = list(first.index[first['ok'] & ~second['ok']])
            only_b = list(first.index[~first['ok'] & second['ok']])
            table.append([f'`{a}` / `{b}`', len(runs), int((first['ok'] & second['ok']).sum()),
                          _runs(only_a), _runs(only_b),
                          _figure(ratio.median()) if len(ratio) else '-',
                          _figure(ratio.max()) if len(ratio) else '-'])
    return ['## Paired: the laws on the same cases', '', _table(
        ['pair', 'cases', 'both succeed', 'first holds, second fails',
         'second holds, first fails', 'settle ratio median', 'settle ratio max'], table), '']


def _runs(runs, shown=8):
    if not runs:
        return '0'
    listed = ', '.join(str(int(r)) for r in runs[:shown])
    return f'{len(runs)} (runs {listed}{", ..." if len(runs) > shown else ""})'


def _plots(out, rows, labels, ok, limit):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    figure, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for column, axis, title in (('settle_tau', axes[0], 'settle tau (settled runs)'),
                                ('swing', axes[1], 'max swing [rad]'),
                                ('compute_median_ms', axes[2], 'compute median [ms]')):
        for label in labels:
            values = rows.loc[rows['law'] == label, column].dropna()
            if len(values):
                axis.hist(values, bins=20, alpha=0.5, label=label)
        if column == 'swing' and limit:
            axis.axvline(limit, color='k', linestyle='--', linewidth=1)
        axis.set_title(title)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(os.path.join(out, 'distributions.png'), dpi=110)
    plt.close(figure)
    figure, axes = plt.subplots(1, len(labels), figsize=(4.2 * len(labels), 3.8),
                                squeeze=False)
    for axis, label in zip(axes[0], labels):
        mine = rows['law'] == label
        for good, colour, name in ((True, 'tab:green', 'success'),
                                   (False, 'tab:red', 'failure')):
            pick = mine & (ok == good)
            axis.scatter(rows.loc[pick, 'x0_2'] + 1.0, rows.loc[pick, 'x0_3'], s=12,
                         c=colour, label=f'{name} ({int(pick.sum())})')
        axis.set_title(label)
        axis.set_xlabel('l at the start')
        axis.set_ylabel("l' at the start")
        axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(os.path.join(out, 'starts.png'), dpi=110)
    plt.close(figure)
