"""The frontier study: the table shown and recomputed, and one row re-solved by the solver."""

import json

import numpy as np
import pytest

from tsr_koopman_ctrl.evaluation.frontier import load_table, table_entry
from tsr_koopman_ctrl.evaluation.starts import TABULATED_STARTS as ALL_STARTS
from lab import frontier as tool
from lab import min_time


def test_show_prints_the_table_and_bad_input_is_one_line(capsys):
    assert tool.main(['--show']) == 0
    out = capsys.readouterr().out
    assert out.count('\n') == 2 + len(ALL_STARTS) and '| 0 | [0.0, 0.0, -0.99, 0.5] |' in out
    assert tool.main(['--start', '11']) == 2
    err = capsys.readouterr().err
    assert err.startswith('frontier: no start 11') and err.count('\n') == 1
    with pytest.raises(SystemExit):
        tool.main(['--start', 'x'])
    assert capsys.readouterr().err.count('\n') == 1


def test_the_page_shows_the_shipped_table(capsys):
    """docs/frontier.md's per-start table is the shipped frontier table, as --show prints it
    (the figures every ratio in the project is taken against)."""
    from conftest import ROOT
    assert tool.main(['--show']) == 0
    shown = capsys.readouterr().out.strip()
    assert shown in (ROOT / 'docs' / 'frontier.md').read_text()


def test_recompute_writes_the_table_format(tmp_path, monkeypatch, capsys):
    """The table writer with the solver replaced by two canned rows (the solver is slow)."""
    plan = {'tensions': np.full(3, 3.0), 'success': True}
    rows = [{'theta_max': None, 'T': 2.5, 'swing': 0.7, 'solve_s': 1.0, 'success': True,
             'zone_tau': 2.4, 'result': plan, 'note': ''},
            {'theta_max': 'min', 'T': 30.0, 'swing': 0.1, 'solve_s': 1.0, 'success': True,
             'zone_tau': 29.0, 'result': plan, 'note': 'least'}]

    def fake_table(x0, progress=None, **options):
        for row in rows:
            progress(row)
        return rows

    monkeypatch.setattr(min_time, 'frontier_table', fake_table)
    monkeypatch.setattr(min_time, 'interval_defects', lambda result: np.zeros((3, 4)))
    out = tmp_path / 'table.json'
    assert tool.main(['--start', '3', '--out', str(out)]) == 0
    assert tool.main(['--start', '5', '--out', str(out)]) == 0   # merged: 3 is kept
    assert 'start 5' in capsys.readouterr().out
    table = json.loads(out.read_text())
    assert [e['x0'] for e in table['starts']] == [list(ALL_STARTS[3]), list(ALL_STARTS[5])]
    assert table['starts'][1]['least_swing']['swing'] == 0.1
    assert set(table['starts'][1]['rows'][0]) == set(load_table()['starts'][0]['rows'][0])
    assert set(table['provenance']) == set(load_table()['provenance'])


@pytest.mark.parametrize('index, theta_max, seed', [(5, None, 0), (7, 0.4, 2)])
def test_one_row_re_solved_matches_the_table_and_flies(index, theta_max, seed):
    """Independent of the table: one seed (~4 s each), then the plan through tsr_sim's RK4."""
    start = ALL_STARTS[index]
    row = next(r for r in table_entry(start)['rows'] if r['theta_max'] == theta_max)
    plan = min_time.min_time_deployment(start, theta_max=theta_max,
                                        guess_weights=min_time.GUESS_WEIGHTS[seed:seed + 1],
                                        duration_scales=(1.0,))
    assert plan['success']
    assert plan['T'] == pytest.approx(row['T'], rel=0.01)
    flown = min_time.replay(start, plan)
    assert np.abs(flown[-1]).max() < 1e-3
    assert np.all(plan['tensions'] >= 0.0) and np.all(plan['tensions'] <= 5.0)
    bound = np.inf if theta_max is None else theta_max + 1e-6
    assert np.abs(flown[:, 0]).max() <= bound
    assert np.abs(min_time.path_thetas(plan)).max() <= bound
    assert min_time.interval_defects(plan).max() < 1e-6
