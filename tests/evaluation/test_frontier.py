"""The minimum-time frontier the product reads: the shipped table and its interpolation."""

import numpy as np
import pytest
from tsr_sim import dynamics

from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, frontier_tau
from tsr_koopman_ctrl.evaluation.frontier import load_table, table_entry
from tsr_koopman_ctrl.evaluation.starts import TABULATED_STARTS as ALL_STARTS


def test_the_table_covers_every_comparison_held_out_and_tuning_start():
    table = load_table()
    assert table['provenance']['command'].startswith('python -m lab.frontier')
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
