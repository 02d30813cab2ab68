"""Full-factorial campaigns: named plant cases over a start list or a start grid, the run ->
(start, case) mapping, the rows' case column and extra figures, bad cases refused in one line.

A cheap law (linear_lqr) and a few dozen steps; the lab's studies (robustness, fallback
region, assurance) are specs of this form.
"""

import math
import os

import numpy as np
import pytest
import yaml

from conftest import ROOT
from tsr_koopman_ctrl.campaign import (Campaign, differences, fly, load_spec, replay,
                                       run_campaign)
from tsr_koopman_ctrl.commands import campaign as command
from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.evaluation.starts import COMPARISON_STARTS

STARTS = [[0.0, 0.0, -0.99, 0.5], [0.1, -0.1, -0.9, 0.5]]
CASES = [{'label': 'nominal'},
         {'label': 'weak, lagging', 'actuator_gain': 0.8, 'actuator_lag': 0.05},
         {'label': 'dispersed lag', 'actuator_lag': {'low': 0.0, 'high': 0.05}}]
SPEC = {'steps': 40, 'seed': 3, 'start': STARTS, 'cases': CASES,
        'plant': {'actuator_gain': {'low': 1.0, 'high': 1.1}},
        'laws': ['linear_lqr'], 'figures': ['final_length_offset', 'tension_max']}


def test_every_start_flies_every_case_and_the_runs_default_to_their_product():
    campaign = Campaign.parse(SPEC)
    assert campaign.runs == len(STARTS) * len(CASES) == 6
    assert [campaign.position(run) for run in range(8)] == [
        (0, 0), (1, 0), (0, 1), (1, 1), (0, 2), (1, 2), (0, 0), (1, 0)]
    for run in range(campaign.runs):
        start, case = campaign.position(run)
        flown = campaign.case(run)
        assert list(flown.x0) == STARTS[start] and flown.plant_case == CASES[case]['label']
    # A case's values replace the common plant's, fixed or dispersed.
    weak, lag = campaign.case(2), campaign.case(4)
    assert (weak.plant['actuator_gain'], weak.plant['actuator_lag']) == (0.8, 0.05)
    assert weak.dispersed == {}
    assert set(lag.dispersed) == {'actuator_gain', 'actuator_lag'}
    assert 1.0 <= lag.plant['actuator_gain'] <= 1.1 and 0.0 <= lag.plant['actuator_lag'] <= 0.05
    assert campaign.dispersed_names() == ['actuator_gain', 'actuator_lag']
    # A box counts as one start: 100 runs per case by default, run n flies case n mod C.
    box = Campaign.parse({**SPEC, 'start': {'low': [0, 0, -0.99, 0.3],
                                            'high': [0.01, 0.01, -0.98, 0.7]}})
    assert box.runs == 300 and [box.position(run)[1] for run in range(4)] == [0, 1, 2, 0]


def test_the_spec_with_cases_reads_back_to_the_same_campaign():
    campaign = Campaign.parse(SPEC)
    stored = yaml.safe_load(yaml.safe_dump(campaign.as_dict()))
    assert stored['cases'][1] == {'label': 'weak, lagging', 'actuator_gain': 0.8,
                                  'actuator_lag': 0.05}
    again = Campaign.parse(stored)
    assert again.as_dict() == campaign.as_dict()
    assert [again.case(run) for run in range(6)] == [campaign.case(run) for run in range(6)]
    # A spec without cases or figures names neither in its canonical form.
    plain = Campaign.parse({'laws': ['linear_lqr'], 'start': STARTS}).as_dict()
    assert 'cases' not in plain and 'figures' not in plain


def test_a_start_grid_is_every_combination_the_last_component_fastest():
    grid = [[-0.3, 0.3], [0.0], [-0.99, -0.7, 0.0], [-0.5, 1.0]]
    campaign = Campaign.parse({'laws': ['linear_lqr'], 'start': {'grid': grid},
                               'cases': CASES[:2]})
    assert len(campaign.start_list) == 12 and campaign.runs == 24
    assert campaign.start_list[:3] == ((-0.3, 0.0, -0.99, -0.5), (-0.3, 0.0, -0.99, 1.0),
                                       (-0.3, 0.0, -0.7, -0.5))
    assert campaign.start_list[-1] == (0.3, 0.0, 0.0, 1.0)
    assert campaign.case(13).x0 == campaign.start_list[1]
    assert campaign.case(13).plant_case == 'weak, lagging'


def test_named_start_sets_and_starts_mix_in_one_list():
    campaign = Campaign.parse({'laws': ['linear_lqr'],
                               'start': ['comparison', [0.1, -0.1, -0.9, 0.5]]})
    assert campaign.start_list == (*COMPARISON_STARTS, (0.1, -0.1, -0.9, 0.5))
    named = Campaign.parse({'laws': ['linear_lqr'], 'start': ['comparison']})
    assert named.start_list == COMPARISON_STARTS


def test_the_rows_carry_their_case_and_the_figures_the_spec_asks_for(tmp_path):
    campaign = Campaign.parse(SPEC)
    rows = run_campaign(campaign, str(tmp_path / 'cases'), workers=1, progress=False)
    assert list(rows['case']) == [CASES[case]['label'] for case in (0, 0, 1, 1, 2, 2)]
    assert list(rows.columns[:5]) == ['run', 'seed', 'case', 'actuator_gain', 'actuator_lag']
    assert list(rows.columns[-2:]) == ['final_length_offset', 'tension_max']
    weak = rows[rows['case'] == 'weak, lagging']
    assert weak['actuator_gain'].isna().all() and weak['actuator_lag'].isna().all()
    # The weak case flown by hand: the same final l - 1 as its row.
    states, tensions = closed_loop(make_controller('linear_lqr'), STARTS[1], 40,
                                   plant={'actuator_gain': 0.8, 'actuator_lag': 0.05,
                                          'seed': int(weak['seed'].iloc[1])})
    assert weak['final_length_offset'].iloc[1] == pytest.approx(states[-1][2], abs=1e-12)
    assert weak['tension_max'].iloc[1] == pytest.approx(max(tensions), abs=1e-12)
    report = open(os.path.join(str(tmp_path / 'cases'), 'report.md')).read()
    assert '## Success per law and plant case' in report
    assert '| `linear_lqr` | weak, lagging | 2 / 2 |' in report
    # Without cases a row has no case column.
    row = fly(Campaign.parse({'laws': ['linear_lqr'], 'steps': 5}), 0, 'linear_lqr')
    assert 'case' not in row and not math.isnan(row['swing'])


def test_a_row_can_carry_its_loop_and_its_replay_compares_it(tmp_path):
    out = str(tmp_path / 'loops')
    spec = {'steps': 30, 'start': STARTS, 'laws': ['linear_lqr'],
            'figures': ['states', 'tensions']}
    rows = run_campaign(Campaign.parse(spec), out, workers=1, progress=False, report=False)
    states, tensions = closed_loop(make_controller('linear_lqr'), STARTS[1], 30,
                                   plant={'seed': int(rows['seed'].iloc[1])})
    assert [list(x) for x in rows['states'].iloc[1]] == states.tolist()
    assert list(rows['tensions'].iloc[1]) == list(tensions)
    again, stored = replay(out, 1, 'linear_lqr')
    assert differences(again, stored) == []
    stored['tensions'] = [*stored['tensions'][:-1], stored['tensions'][-1] + 1e-9]
    assert differences(again, stored) == ['tensions']


BAD_CASES = {
    'cases not a list': ({'cases': {'label': 'a'}}, 'cases must be a non-empty list'),
    'an empty list': ({'cases': []}, 'cases must be a non-empty list'),
    'a case without a label': ({'cases': [{'actuator_gain': 0.8}]},
                               'cases 0: a case is {label: ..., plant parameters}'),
    'a label that is not text': ({'cases': [{'label': 0.8}]}, 'label must be a line of text'),
    'two cases with one label': ({'cases': [{'label': 'a'}, {'label': 'a'}]},
                                 "two cases share the label 'a'"),
    'an unknown plant parameter': ({'cases': [{'label': 'a', 'actuator_gian': 0.8}]},
                                   "did you mean 'actuator_gain'"),
    'a value out of its range': ({'cases': [{'label': 'a', 'eccentricity': 2.0}]},
                                 'eccentricity must be in'),
    'an empty range': ({'cases': [{'label': 'a', 'actuator_lag': {'low': 0.1, 'high': 0.1}}]},
                       'empty range'),
    'a parameter the campaign sets': ({'cases': [{'label': 'a', 'seed': 3}]},
                                      'set by the campaign'),
    'an unknown figure': ({'figures': ['final_lenght_offset']},
                          "did you mean 'final_length_offset'"),
    'a grid with three components': ({'start': {'grid': [[0.0], [0.0], [-0.9]]}},
                                     'grid needs 4 lists of values'),
    'a grid start outside the domain': ({'start': {'grid': [[0.0], [0.0], [-1.0], [0.5]]}},
                                        'outside the model domain'),
    'a grid beside a box': ({'start': {'grid': [[0.0], [0.0], [-0.9], [0.5]],
                                       'low': [0, 0, -0.9, 0.5]}}, 'a grid takes no low'),
    'an unknown start set among starts': ({'start': ['comparisn', [0, 0, -0.9, 0.5]]},
                                          "no start set 'comparisn'"),
}


@pytest.mark.parametrize('spec, says', BAD_CASES.values(), ids=list(BAD_CASES))
def test_a_bad_case_grid_or_figure_is_refused_in_one_line_before_any_run(
        spec, says, tmp_path, capsys):
    path = tmp_path / 'spec.yaml'
    path.write_text(yaml.safe_dump({'laws': ['linear_lqr'], **spec}))
    out = tmp_path / 'out'
    with pytest.raises(SystemExit) as refused:
        command.main(['--spec', str(path), '--out', str(out)])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith('campaign: error: ') and says in err[-1], err[-1]
    assert not out.exists()
    with pytest.raises(ValueError) as error:
        load_spec(str(path))
    assert says in str(error.value) and '\n' not in str(error.value)


@pytest.mark.parametrize('path', ['lab/campaigns/robustness.yaml',
                                  'lab/campaigns/fallback_region.yaml',
                                  *(f'lab/campaigns/assurance/{part}.yaml' for part in (
                                      'nominal', 'swing', 'robust', 'monitor',
                                      'monitor_nudged'))])
def test_the_lab_s_grids_load(path):
    campaign = load_spec(str(ROOT / path))
    starts = len(campaign.start_list)
    assert campaign.runs == starts * max(1, len(campaign.cases))


@pytest.mark.parametrize('low, high', [(-0.995, 0.0), (0.3, 1.5)])
def test_dense_low_draws_follow_their_density_and_stay_in_the_box(low, high):
    from scipy.stats import kstest
    from tsr_koopman_ctrl.campaign.spec import Dispersion
    dispersion = Dispersion(low, high, 'dense_low')
    draws = np.array([dispersion.draw(u) for u in np.random.default_rng(3).random(4000)])
    assert draws.min() >= low and draws.max() <= high
    # The density 2 (high - v) / w^2, written independently as its CDF.
    width = high - low
    cdf = lambda v: 1.0 - ((high - np.asarray(v)) / width) ** 2   # noqa: E731
    assert kstest(draws, cdf).pvalue > 0.01
    assert np.mean(draws < low + 0.293 * width) == pytest.approx(0.5, abs=0.03)
    assert kstest(draws, 'uniform', args=(low, width)).pvalue < 1e-6


def test_the_safety_campaign_s_specs_load_and_judge_the_swing_as_the_studies_do():
    """The dispersed part's swing limit is the bound plus the studies' tolerance; the domain
    part flies 1000 cases with no swing bound, its tether length dense at the short end."""
    from tsr_koopman_ctrl.evaluation.figures import SWING_TOLERANCE
    dispersed = load_spec(os.path.join(ROOT, 'lab', 'campaigns', 'safety_filter.yaml'))
    assert dispersed.swing_limit == pytest.approx(0.4 + SWING_TOLERANCE)
    domain = load_spec(os.path.join(ROOT, 'lab', 'campaigns', 'safety_filter_domain.yaml'))
    assert domain.runs == 1000 and domain.swing_limit is None
    assert domain.start_box[2].distribution == 'dense_low'
    assert load_spec(os.path.join(ROOT, 'lab', 'campaigns', 'safety_filter_domain.yaml'),
                     runs=20).runs == 20


@pytest.mark.parametrize('spec, published', [
    ('fallback_commands_domain.yaml', 'safety_filter_domain.yaml'),
    ('fallback_commands_swing.yaml', 'safety_filter.yaml')])
def test_the_fallback_commands_specs_fly_the_safety_campaign_s_cases(spec, published):
    """Run n of each is run n of the published campaign (docs/supervisor.md compares them)."""
    mine = load_spec(os.path.join(ROOT, 'lab', 'campaigns', spec), runs=1000)
    theirs = load_spec(os.path.join(ROOT, 'lab', 'campaigns', published), runs=1000)
    assert mine.swing_limit == theirs.swing_limit
    for run in (0, 4, 104, 641, 999):
        assert tuple(mine.case(run).x0) == tuple(theirs.case(run).x0)
        assert mine.case(run).plant == theirs.case(run).plant
    assert {e.label for e in mine.laws} == {'filtered', 'checked', 'physics'}
