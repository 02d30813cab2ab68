"""The robustness grid (lab/campaigns/robustness.yaml, `lab.robustness`): the command, shortened
so that nothing settles (its table must still be written, with each start's final length
offset), and the default law's headline on a reduced grid."""

import json

import pytest

from tsr_koopman_ctrl.campaign import fly
from tsr_koopman_ctrl.control import closed_loop, make_controller
from lab import robustness


def test_a_grid_where_nothing_settles_reports_the_final_offsets(tmp_path):
    page = tmp_path / 'page.md'
    page.write_text('<!-- robustness:begin -->\n<!-- robustness:end -->\n')
    out = tmp_path / 'robustness'
    assert robustness.main(['--law', 'linear_lqr', '--steps', '200', '--workers', '2',
                            '--out', str(out), '--page', str(page)]) == 0
    table = json.loads((out / 'robustness.json').read_text())
    assert [(r['control'], r['case']) for r in table[:2]] == [
        ('bare', 'nominal'), ('bare', 'gain 0.8, lag 0.05')]
    nominal = table[0]
    campaign = robustness.load(['linear_lqr'], 200)
    x0 = campaign.start_list[0]
    states, _ = closed_loop(make_controller('linear_lqr', observer={'disturbance': 'none'}),
                            x0, 200)
    first = nominal['starts'][0]
    assert first['x0'] == list(x0) and first['settle_tau'] is None
    assert first['final_length_offset'] == pytest.approx(states[-1][2], abs=1e-12)
    assert f"- ({states[-1][2]:+.3f})" in (out / 'robustness.md').read_text()
    # The page: nothing settled in 200 steps, of the 8 disturbed cases x 6 starts
    shown = page.read_text()
    assert robustness.page_tables(table, campaign) in shown
    assert '| `linear_lqr`, bare | -, -, -, -, -, - | 0 / 48 | 0 | - |' in shown
    assert '| actuator gain (lag 0.05 tau) | (0.0, 0.0, -0.99, 0.5) |' in shown
    # Flown again, the grid is resumed: nothing new flown, the same table.
    assert robustness.main(['--law', 'linear_lqr', '--steps', '200', '--workers', '1',
                            '--out', str(out)]) == 0
    assert json.loads((out / 'robustness.json').read_text()) == table
    # Another grid into the same directory is refused in one line.
    assert robustness.main(['--law', 'linear_lqr', '--steps', '201', '--out', str(out)]) == 2


#: The grid's figures for the default law (docs/robustness.md), measured with the spec's runs
#: from the paper's start, 2000 steps: nominal 3.49 tau; gain 0.8 and lag 0.05 3.99; gain 1.2,
#: lag 0.05 and noise 1e-3 4.13. The bare law settles in neither.
NOMINAL_BOUND = 3.7              # koopman_mpc and linear_lqr, offset-free: 4.83 and 4.90
DISTURBED_BOUND = 1.25           # x the nominal: their 4.8-5.2 would fail it


@pytest.mark.timeout(1200)
def test_the_default_law_settles_in_every_disturbed_case_of_a_reduced_grid():
    """The headline of docs/robustness.md (koopman_nmpc, offset-free, settles in every
    disturbed case) on two cases of its grid, an actuator too weak and one too strong, both
    lagging, one with sensor noise: each settles within 1.25x the nominal time, which is
    itself under 3.7 tau; the bare law, a clearly worse one here, settles in neither. 800
    steps: each settles by 4.2 tau and stays to the end."""
    campaign = robustness.load(steps=800)
    starts = len(campaign.start_list)
    run = {case.label: index * starts for index, case in enumerate(campaign.cases)}
    nominal = fly(campaign, run['nominal'], 'koopman_nmpc')['settle_tau']
    assert nominal <= NOMINAL_BOUND
    for case in ('gain 0.8, lag 0.05', 'gain 1.2, lag 0.05, noise 0.001'):
        settled = fly(campaign, run[case], 'koopman_nmpc')['settle_tau']
        assert settled <= DISTURBED_BOUND * nominal, (case, settled)
        bare = fly(campaign, run[case], 'koopman_nmpc_bare')['settle_tau']
        assert bare != bare, (case, bare)          # NaN: not settled
