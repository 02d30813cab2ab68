"""The robustness grid command, shortened so that nothing settles: its table must still be
written, with each start's final length offset."""

import json

import pytest

from tsr_koopman_ctrl.control import closed_loop, make_controller
from lab import robustness


def test_a_grid_where_nothing_settles_reports_the_final_offsets(tmp_path):
    assert robustness.main(['--law', 'linear_lqr', '--steps', '200', '--out',
                            str(tmp_path)]) == 0
    rows = json.loads((tmp_path / 'robustness.json').read_text())
    nominal = next(r for r in rows if r['control'] == 'bare' and r['case'] == 'nominal')
    x0 = robustness.STARTS[0]
    states, _ = closed_loop(make_controller('linear_lqr', observer={'disturbance': 'none'}),
                            x0, 200)
    first = nominal['starts'][0]
    assert first['settle_tau'] is None
    assert first['final_length_offset'] == pytest.approx(states[-1][2], abs=1e-12)
    assert f"- ({states[-1][2]:+.3f})" in (tmp_path / 'robustness.md').read_text()
