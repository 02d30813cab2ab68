"""The comparison command and the settings presets."""

import json

import pytest

from tsr_koopman_ctrl.control.registry import preset
from tsr_koopman_ctrl.evaluation import closed_loop_figures, COMPARISON_STARTS
from lab import compare


def test_the_untuned_preset_holds_the_settings_before_tuning():
    untuned = preset('untuned')
    assert untuned['linear_lqr'] == {'q': [1.0, 1.0, 1.0, 1.0], 'r': 1.0}
    assert untuned['koopman_lqr']['r'] == 15.0 and untuned['koopman_mpc']['horizon'] == 5
    with pytest.raises(ValueError, match="no settings preset 'bogus'"):
        preset('bogus')


def test_compare_scores_every_start_with_the_loop_s_own_figures(tmp_path):
    assert compare.main(['--law', 'linear_lqr', '--presets', 'untuned', '--steps', '1200',
                         '--out', str(tmp_path)]) == 0
    rows = json.loads((tmp_path / 'comparison.json').read_text())
    assert len(rows) == 9 and {r['starts'] for r in rows} == {'comparison', 'held-out'}
    from tsr_koopman_ctrl.control import make_controller
    first = closed_loop_figures(make_controller('linear_lqr', q=[1.0] * 4, r=1.0),
                                COMPARISON_STARTS[0], 1200)
    assert rows[0]['settle_tau'] == first['settle_tau'] and rows[0]['swing'] == first['swing']
    assert rows[0]['compute_median_us'] > 0.0
    assert '| linear_lqr | untuned |' in (tmp_path / 'comparison.md').read_text()
    assert (tmp_path / 'ratios.png').stat().st_size > 0


def test_a_swing_bound_goes_to_the_laws_that_take_one(tmp_path):
    assert compare.main(['--law', 'linear_lqr', 'koopman_mpc', '--presets', 'tuned',
                         '--theta-max', '0.5', '--steps', '300', '--out', str(tmp_path)]) == 0
    rows = json.loads((tmp_path / 'comparison.json').read_text())
    assert {r['law'] for r in rows} == {'koopman_mpc'} and len(rows) == 9
    assert {r['preset'] for r in rows} == {'tuned, |theta| <= 0.5'}
    from tsr_koopman_ctrl.control import make_controller
    first = closed_loop_figures(make_controller('koopman_mpc', theta_max=0.5),
                                COMPARISON_STARTS[0], 300)
    assert rows[0]['swing'] == first['swing']
    # The bound's label keeps its table row in columns: every line as many cells as the head.
    table = (tmp_path / 'comparison.md').read_text().split('\n\n')[0].splitlines()
    assert '| tuned, \\|theta\\| <= 0.5 |' in table[2]
    assert len({line.replace('\\|', '').count('|') for line in table}) == 1
    # None of the laws takes one: an error, not an empty table.
    assert compare.main(['--law', 'linear_lqr', '--theta-max', '0.4', '--steps', '10',
                         '--out', str(tmp_path / 'none')]) == 2
    assert not (tmp_path / 'none').exists()


def test_a_law_with_hand_picked_defaults_runs_once_unless_a_preset_names_it(
        tmp_path, monkeypatch, capsys):
    # physics_nmpc's role, played by the fast linear_lqr: 'tuned' and a preset without it give
    # its defaults once; a preset that names it ('untuned' here) gives its own rows.
    monkeypatch.setattr(compare, 'NOT_TUNED', {'linear_lqr'})
    without = tmp_path / 'without.yaml'
    without.write_text('/**:\n  ros__parameters:\n    koopman_mpc:\n      horizon: 4\n')
    assert compare.main(['--law', 'linear_lqr', '--presets', 'tuned', str(without), 'untuned',
                         '--steps', '200', '--out', str(tmp_path)]) == 0
    rows = json.loads((tmp_path / 'comparison.json').read_text())
    assert [r['preset'] for r in rows] == ['defaults'] * 9 + ['untuned'] * 9
    # ... and the untuned rows ran the untuned settings, not the defaults again.
    assert all(a['swing'] != b['swing'] for a, b in zip(rows[:9], rows[9:]))
    # A preset file that does not name a tuned law leaves it out (rather than running its
    # defaults under the file's name); naming none of the laws compared, it is an error, not
    # an empty table.
    (tmp_path / 'comparison.json').unlink()
    assert compare.main(['--law', 'fractional_pd', '--presets', str(without), '--steps', '200',
                         '--out', str(tmp_path)]) == 2
    assert capsys.readouterr().err == (
        f"compare: --presets {without}: sets none of the laws compared (['fractional_pd']), "
        "only ['koopman_mpc']\n")
    assert not (tmp_path / 'comparison.json').exists()
    # A repeated preset runs once.
    assert compare.main(['--law', 'linear_lqr', '--presets', 'untuned', 'untuned',
                         '--steps', '200', '--out', str(tmp_path)]) == 0
    assert len(json.loads((tmp_path / 'comparison.json').read_text())) == 9


def test_the_ratio_tuned_preset_holds_each_law_s_tuning_result():
    from conftest import ROOT
    from tsr_koopman_ctrl.control import CONTROLLERS
    ratio_tuned = preset('tuned_ratio')
    assert set(ratio_tuned) == set(CONTROLLERS)
    # The settings each study held fixed, as its name spells them.
    fixed_in_study = {'koopman_lqr': '_state-weight-state_model-koopman-block-fast',
                      'koopman_mpc': '_model-koopman-block_horizon-30'}
    folder = {'koopman_nmpc': 'koopman_nmpc/'}    # its search ran over four sessions
    for law, values in ratio_tuned.items():
        fixed = fixed_in_study.get(law, '')
        record = (ROOT / 'docs' / 'tuning' /
                  f'{folder.get(law, "")}{law}{fixed}_worst-ratio_swing0.8.json')
        assert json.loads(record.read_text())['trials'] >= 100, law   # the same effort
        best = json.loads(record.read_text())['best_settings']
        for name, value in best.items():
            if isinstance(value, str):
                assert values[name] == value
            else:   # the file holds 4 significant digits
                assert values[name] == pytest.approx(value, rel=5e-4), (law, name)


def test_the_cross_term_preset_holds_each_law_s_best_search():
    """config/tuned_cross.yaml: per law, the best result on the tuning starts of its 400-trial
    searches with the state weight's cross terms (docs/tuning/q_cross/seed*/, flat or graded
    penalty; the 60-step and the continued MPC studies are experiments beside them), except
    koopman_lqr, whose preset plans on koopman_block_fast: the one search on that model
    (block_fast/, run on its scratch copy, the same weights file)."""
    from conftest import ROOT
    tuned_cross = preset('tuned_cross')
    assert set(tuned_cross) == {'linear_lqr', 'koopman_lqr', 'koopman_mpc'}
    fixed_in_study = {'koopman_lqr': '_state-weight-state',
                      'koopman_mpc': '_model-koopman-block_horizon-30'}
    searches = ROOT / 'docs' / 'tuning' / 'q_cross'
    for law, values in tuned_cross.items():
        name = f'{law}{fixed_in_study.get(law, "")}_with-q_cross_worst-ratio*_swing0.8.json'
        records = [json.loads(path.read_text()) for path in searches.glob(f'seed*/{name}')]
        assert len(records) >= 3, law     # three searches at least, the same for every law
        if law == 'koopman_lqr':
            records = [json.loads((searches / 'block_fast' / 'koopman_lqr_r095.json')
                                  .read_text())]
            assert records[0]['best_settings'].pop('model').endswith('ft_r0.95')
            assert values.pop('model') == 'koopman_block_fast'
        assert all(r['trials'] <= 401 for r in records), law
        best = min(records, key=lambda r: r['best_value'])['best_settings']
        assert len(best['q_cross']) == 6 and any(best['q_cross'])
        for setting, value in best.items():
            if isinstance(value, str):
                assert values[setting] == value
            else:   # the file holds 4 significant digits
                assert values[setting] == pytest.approx(value, rel=5e-4), (law, setting)


def test_the_committed_comparison_is_what_the_command_runs_by_default():
    """docs/comparison holds every law but the slow koopman_nmpc, which has its own folders
    (700 steps), under the default presets: the README's command without options."""
    from conftest import ROOT
    docs = ROOT / 'docs' / 'comparison'
    rows = json.loads((docs / 'comparison.json').read_text())
    defaults = compare.parser().parse_args([])
    assert 'koopman_nmpc' not in defaults.law
    assert sorted({r['law'] for r in rows}) == sorted(defaults.law)
    assert {r['preset'] for r in rows} == set(defaults.presets) | {'defaults'}
    assert {r['law'] for r in rows if r['preset'] == 'defaults'} == compare.NOT_TUNED - {
        'koopman_nmpc'}
    for folder in ('koopman_nmpc', 'koopman_nmpc_tuned_ratio', 'koopman_nmpc_swing0.4',
                   'koopman_nmpc_tuned_ratio_swing0.4'):
        nmpc = json.loads((docs / folder / 'comparison.json').read_text())
        assert {r['law'] for r in nmpc} == {'koopman_nmpc'} and len(nmpc) == 9
