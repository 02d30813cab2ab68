"""The comparison command and the settings presets."""

import json

import pytest

from tsr_koopman_ctrl.control.registry import law_class, preset
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
    page = tmp_path / 'page.md'
    page.write_text('# The page\n<!-- swing:begin -->\n<!-- swing:end -->\n')
    out = tmp_path / 'swing'
    assert compare.main(['--law', 'linear_lqr', 'koopman_mpc', '--presets', 'tuned',
                         '--theta-max', '0.5', '--steps', '300', '--out', str(out),
                         '--page', str(page)]) == 0
    rows = json.loads((out / 'comparison.json').read_text())
    # The page's tables, from the same rows: where the law held the bound and where not
    shown = page.read_text()
    assert compare.page_tables(rows, 0.5) in shown
    held = sum(r['swing'] <= 0.505 for r in rows)
    assert f"| `koopman_mpc` | tuned, \\|theta\\| <= 0.5 | {held}/9 |" in shown
    for r in rows:
        assert f"{r['swing']:.2f}" in shown
    assert {r['law'] for r in rows} == {'koopman_mpc'} and len(rows) == 9
    assert {r['preset'] for r in rows} == {'tuned, |theta| <= 0.5'}
    from tsr_koopman_ctrl.control import make_controller
    first = closed_loop_figures(make_controller('koopman_mpc', theta_max=0.5),
                                COMPARISON_STARTS[0], 300)
    assert rows[0]['swing'] == first['swing']
    # The bound's label keeps its table row in columns: every line as many cells as the head.
    table = (out / 'comparison.md').read_text().split('\n\n')[0].splitlines()
    assert '| tuned, \\|theta\\| <= 0.5 |' in table[2]
    assert len({line.replace('\\|', '').count('|') for line in table}) == 1
    # None of the laws takes one: an error, not an empty table.
    assert compare.main(['--law', 'linear_lqr', '--theta-max', '0.4', '--steps', '10',
                         '--out', str(tmp_path / 'none')]) == 2
    assert not (tmp_path / 'none').exists()


def test_a_page_without_the_markers_is_refused_before_the_runs(tmp_path, capsys):
    page = tmp_path / 'page.md'
    page.write_text('# no markers\n')
    assert compare.main(['--law', 'linear_lqr', '--out', str(tmp_path / 'comparison'),
                         '--page', str(page)]) == 2
    assert 'has no <!-- comparison:begin -->' in capsys.readouterr().err
    assert not (tmp_path / 'comparison').exists()


def test_a_preset_file_shows_the_laws_it_names(tmp_path, capsys):
    """A preset file that does not name a law compared leaves it out (rather than running its
    defaults under the file's name); naming none of them, it is an error, not an empty table."""
    without = tmp_path / 'without.yaml'
    without.write_text('/**:\n  ros__parameters:\n    koopman_mpc:\n      horizon: 4\n')
    assert compare.main(['--law', 'linear_lqr', 'koopman_mpc', '--presets', 'tuned',
                         str(without), 'untuned', '--steps', '200', '--out',
                         str(tmp_path / 'three')]) == 0
    rows = json.loads((tmp_path / 'three' / 'comparison.json').read_text())
    lqr = [r for r in rows if r['law'] == 'linear_lqr']
    assert [r['preset'] for r in lqr] == ['tuned'] * 9 + ['untuned'] * 9
    # ... and the untuned rows ran the untuned settings, not the defaults again.
    assert all(a['swing'] != b['swing'] for a, b in zip(lqr[:9], lqr[9:]))
    assert [r['preset'] for r in rows if r['law'] == 'koopman_mpc'] == \
        ['tuned'] * 9 + [str(without)] * 9 + ['untuned'] * 9
    capsys.readouterr()
    assert compare.main(['--law', 'fractional_pd', '--presets', str(without), '--steps', '200',
                         '--out', str(tmp_path / 'none')]) == 2
    assert capsys.readouterr().err == (
        f"compare: --presets {without}: sets none of the laws compared (['fractional_pd']), "
        "only ['koopman_mpc']\n")
    assert not (tmp_path / 'none').exists()
    # A repeated preset runs once.
    assert compare.main(['--law', 'linear_lqr', '--presets', 'untuned', 'untuned',
                         '--steps', '200', '--out', str(tmp_path / 'once')]) == 0
    assert len(json.loads((tmp_path / 'once' / 'comparison.json').read_text())) == 9
    # Flown again into the same directory, the campaign is read back, not flown; another
    # comparison there is refused in one line.
    assert compare.main(['--law', 'linear_lqr', '--presets', 'untuned', '--steps', '200',
                         '--out', str(tmp_path / 'once')]) == 0
    assert compare.main(['--law', 'linear_lqr', '--presets', 'tuned', '--steps', '200',
                         '--out', str(tmp_path / 'once')]) == 2
    assert 'the spec differs' in capsys.readouterr().err


def docs_table(page, head):
    """The markdown table of a docs page whose header row starts with `head`: one
    {column: cell} per row, the cells stripped of their code quotes."""
    from conftest import ROOT
    lines = (ROOT / 'docs' / page).read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith(head))
    rows = []
    for line in lines[first:]:
        if not line.startswith('|'):
            break
        rows.append([cell.strip().strip('`') for cell in line.strip('|').split(' | ')])
    columns = rows[0]
    return [dict(zip(columns, cells)) for cells in rows[2:]]


#: docs/tuning.md: the search behind each preset entry, and the cross-term searches.
PRESET_ROWS = docs_table('tuning.md', '| preset | law | search |')
CROSS_SEARCHES = docs_table('tuning.md', '| search | law | trials |')


def documented(preset_name):
    """{law: (the row, its settings)} of a preset in docs/tuning.md."""
    return {row['law']: (row, json.loads(row['settings']))
            for row in PRESET_ROWS if row['preset'] == preset_name}


def assert_same_settings(law, values, settings):
    assert set(values) == set(settings), law
    for name, value in settings.items():
        if isinstance(value, str):
            assert values[name] == value, (law, name)
        else:   # both hold 4 significant digits
            assert values[name] == pytest.approx(value, rel=5e-4), (law, name)


#: The laws whose defaults share one cost (docs/tuning.md): the physics NMPC measures what the
#: learned model costs, so it flies the learned NMPC's weights and was given no search of its own.
SHARED_COST = {'physics_nmpc': 'koopman_nmpc'}


def test_the_defaults_are_each_law_s_search_for_the_ratio():
    """What README.md and docs/tuning.md say of the defaults: each law's defaults are the best
    of its own search of 100 trials at least for the largest frontier ratio, except the physics
    NMPC, which shares the learned NMPC's weights (docs/tuning.md records each row; the records
    themselves are regenerated by lab/manifest.yaml's commands)."""
    from tsr_koopman_ctrl.control import CONTROLLERS
    records = documented('defaults')
    assert set(records) == set(CONTROLLERS)
    for law, (row, settings) in records.items():
        if law in SHARED_COST:
            owner = SHARED_COST[law]
            assert row['search'].startswith(f'{owner}\'s'), (law, row['search'])
            assert settings == records[owner][1], law      # the same weights as its owner's
        else:
            study = row['search'].split('`')[0].split(',')[0]
            assert study.startswith(law + '_') and study.endswith('_worst-ratio_swing0.8'), \
                (law, row['search'])                      # its own ratio search, named
            assert int(row['trials']) >= 100, law
        defaults = law_class(law).Settings()
        values = {name: list(value) if isinstance(value, tuple) else value
                  for name, value in ((name, getattr(defaults, name)) for name in settings)}
        assert_same_settings(law, values, settings)


def test_the_settle_tuned_preset_holds_each_law_s_search_for_the_settle_time():
    """config/tuned_settle.yaml: every entry is the best of its law's 60-trial search for the
    mean settle time, as docs/tuning.md records it."""
    tuned_settle = preset('tuned_settle')
    records = documented('tuned_settle')
    assert set(records) == set(tuned_settle)
    for law, values in tuned_settle.items():
        row, settings = records[law]
        assert int(row['trials']) >= 60 and 'worst-ratio' not in row['search'], law
        assert_same_settings(law, values, settings)


def test_the_cross_term_preset_holds_each_law_s_best_search():
    """config/tuned_cross.yaml: per law, the best result on the tuning starts of its 400-trial
    searches with the state weight's cross terms (flat or graded penalty; the 60-step and the
    continued MPC studies are experiments beside them), except koopman_lqr, whose preset plans
    on koopman_block_fast: the one search on that model. docs/tuning.md lists the searches and
    the settings each preset entry holds."""
    tuned_cross = preset('tuned_cross')
    assert set(tuned_cross) == {'linear_lqr', 'koopman_lqr', 'koopman_mpc'}
    records = documented('tuned_cross')
    assert set(records) == set(tuned_cross)
    for law, values in tuned_cross.items():
        candidates = [row for row in CROSS_SEARCHES
                      if row['law'] == law and row['candidate'] == 'yes']
        assert len(candidates) >= 3, law     # three searches at least, the same for every law
        assert all(int(row['trials']) <= 401 for row in candidates), law
        row, settings = records[law]
        if law == 'koopman_lqr':
            assert row['search'] == 'q_cross/block_fast'
            assert settings['model'] == values['model'] == 'koopman_block_fast'
        else:
            best = min(candidates, key=lambda row: float(row['tuning starts']))
            assert row['search'] == best['search'], law
            assert row['tuning starts'] == best['tuning starts'], law
        assert len(settings['q_cross']) == 6 and any(settings['q_cross'])
        assert_same_settings(law, values, settings)


def test_the_comparison_page_shows_what_the_command_runs_by_default():
    """docs/comparison.md's headline table has a column for every law the command runs without
    options (every law), and the page shows that command."""
    from conftest import ROOT
    from tsr_koopman_ctrl.control import CONTROLLERS
    defaults = compare.parser().parse_args([])
    assert sorted(defaults.law) == sorted(CONTROLLERS)
    assert defaults.presets == ['untuned', 'tuned', 'tuned_settle']
    page = (ROOT / 'docs' / 'comparison.md').read_text()
    regenerated = page[page.index('## The comparison, regenerated'):].splitlines()
    head = next(line for line in regenerated if line.startswith('| x0 | `'))
    columns = [cell.strip().strip('`') for cell in head.strip('|').split('|')][1:]
    assert sorted(columns) == sorted(defaults.law)
    assert 'python -m lab.compare --out lab/results/comparison ' in page
