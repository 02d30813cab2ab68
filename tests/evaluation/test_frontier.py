"""The minimum-time frontier: the shipped table, its interpolation, and one row re-solved."""

import json

import numpy as np
import pytest
from tsr_sim import dynamics

from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, frontier_tau, min_time
from tsr_koopman_ctrl.evaluation.frontier import load_table, table_entry
from tsr_koopman_ctrl.evaluation.starts import TABULATED_STARTS as ALL_STARTS
from tsr_koopman_ctrl.tools import frontier as tool


def test_the_table_covers_every_comparison_held_out_and_tuning_start():
    table = load_table()
    assert table['provenance']['command'].startswith('python -m tsr_koopman_ctrl.tools.frontier')
    assert len(table['starts']) == len(ALL_STARTS)
    for start in ALL_STARTS:
        entry = table_entry(start)
        assert entry is not None and entry['u_max'] == dynamics.TENSION_LIMIT
        free = next(r for r in entry['rows'] if r['theta_max'] is None)
        assert free['success'] and 2.0 < free['T'] < 3.0
        assert entry['least_swing']['success']
        assert all(r['max_defect'] < 1e-6 for r in entry['rows'] if r['success'])


def test_frontier_is_monotone_in_the_swing_and_flat_past_the_free_optimum():
    for start in ALL_STARTS:
        entry = table_entry(start)
        free = next(r for r in entry['rows'] if r['theta_max'] is None)
        swings = np.linspace(entry['least_swing']['swing'], 1.5, 300)
        taus = np.array([frontier_tau(start, s) for s in swings])
        assert np.all(np.diff(taus) <= 1e-12), start
        assert frontier_tau(start, free['swing']) == pytest.approx(free['T'], abs=1e-9)
        assert frontier_tau(start, 2.0) == pytest.approx(free['T'], abs=1e-9)
        # Each solved bound is met exactly, between them the estimate lies in between.
        for row in entry['rows']:
            if row['success'] and row['theta_max'] is not None and row['note'] == '':
                assert frontier_tau(start, row['swing']) == pytest.approx(row['T'], rel=1e-6)


def test_frontier_of_the_paper_start_against_the_reference_values():
    start = COMPARISON_STARTS[0]
    assert frontier_tau(start, 0.8) == pytest.approx(3.29, abs=0.01)
    assert frontier_tau(start, 0.4) == pytest.approx(8.84, abs=0.01)
    assert frontier_tau(start, 1.2) == pytest.approx(2.74, abs=0.01)
    # Linear between the solved bounds 0.4 and 0.5.
    assert frontier_tau(start, 0.45) == pytest.approx((8.8406 + 5.8432) / 2, abs=1e-3)
    # With u <= 5 the paper start cannot hold 0.3 rad: no frontier below its least swing.
    assert frontier_tau(start, 0.3) is None
    least = table_entry(start)['least_swing']['swing']
    assert 0.3 < least < 0.4 and frontier_tau(start, least) is not None


def test_no_frontier_for_an_untabulated_start():
    assert frontier_tau((0.0, 0.0, -0.5, 0.1), 0.8) is None
    assert table_entry(np.array(COMPARISON_STARTS[0])) is not None   # numpy start found


@pytest.mark.parametrize('swing', [float('nan'), -0.1, float('inf')])
def test_a_swing_that_is_not_an_angle_is_refused(swing):
    with pytest.raises(ValueError, match='swing must be a finite angle >= 0'):
        frontier_tau(COMPARISON_STARTS[0], swing)     # was NaN, or a number for -0.1


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


def test_symbolic_rk4_is_the_simulator_s_rk4():
    import casadi
    x, u = casadi.SX.sym('x', 4), casadi.SX.sym('u')
    end, path = min_time.symbolic_rk4(x, u, 0.05, 5)
    step = casadi.Function('step', [x, u], [end])
    x0 = np.array([0.1, -0.2, -0.9, 0.5])
    assert len(path) == 5
    np.testing.assert_allclose(np.asarray(step(x0, 2.0)).ravel(),
                               dynamics.rk4_step(x0, 2.0, 0.05, 5), atol=1e-12)
