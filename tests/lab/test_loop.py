"""The data-driven loop command end to end, shortened: real DDS deployments, real bags, one
round of retraining."""

import json

import numpy as np
import pytest

from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS, HELD_OUT_STARTS
from tsr_koopman_ctrl.learning import multistep_errors
from tsr_koopman_ctrl.bag.checks import find_bags
from tsr_koopman_ctrl.learning.recorded import read_bags, windows_dataset
from tsr_koopman_ctrl.model import LiftedModel
from lab import data_loop as loop

pytestmark = pytest.mark.ros


@pytest.mark.timeout(900)          # 14 deployments and a retraining: 3 min on 2 loaded cores
def test_one_round_deploys_records_retrains_and_reports(tmp_path, ros_namespace):
    """Every deployment on a domain of its own (Deployment reserves one), in the test's
    namespace."""
    out = tmp_path / 'loop'
    marker = 'loop_actuator_weak'
    page = tmp_path / 'docs' / 'data_loop.md'
    page.parent.mkdir()
    page.write_text(f'intro\n<!-- {marker}:begin -->\nstale\n<!-- {marker}:end -->\nend\n')
    assert loop.main(['--plant', 'actuator_weak', '--rounds', '1', '--steps', '300',
                      '--epochs', '1', '--out', str(out), '--namespace', ros_namespace,
                      '--page', str(page)]) == 0
    work = out / 'actuator_weak'
    result = json.loads((work / 'report.json').read_text())
    assert [r['round'] for r in result['rounds']] == [0, 1]
    # The main job's law from its own model, as deploy flies it.
    assert result['law'] == 'koopman_nmpc' and result['start_model'] == 'koopman_retrieval'
    assert (work / 'rounds.png').stat().st_size > 0
    report = (work / 'report.md').read_text()
    assert '| 1 | `round1` |' in report
    # The page shows the report and the plot, beside it in figures/.
    assert page.read_text() == (f'intro\n<!-- {marker}:begin -->\n{report.rstrip()}\n'
                                f'<!-- {marker}:end -->\nend\n')
    figure = page.parent / 'figures' / f'{marker}.png'
    assert figure.read_bytes() == (work / 'rounds.png').read_bytes()

    # The bags say what ran: the plant variant, the excitation on the training runs only.
    train = sorted((work / 'bags' / 'round1_train').iterdir())
    assert len(train) == len(COMPARISON_STARTS)
    recorded = read_loop(str(train[0]))
    assert recorded.namespace == ros_namespace
    assert recorded.run_info['simulator']['plant'] == 'actuator_weak'
    assert recorded.run_info['simulator']['variant']['actuator_gain'] == 0.9
    assert np.any(recorded.excitation != 0.0)
    assert len(list((work / 'bags' / 'held_out').iterdir())) == len(HELD_OUT_STARTS)

    # The retrained model's provenance: the training bags, never the held-out ones.
    meta = json.loads((work / 'models' / 'round1' / 'model.json').read_text())
    used = {b['path'] for b in meta['retrain']['bags']}
    assert used == {str(p) for p in train}
    assert meta['retrain']['stride'] == 3

    # The reported errors are the models' own on the held-out bags' windows, recomputed here.
    held, bad = read_bags(find_bags([str(work / 'bags' / 'held_out')]))
    assert not bad
    data = windows_dataset(held)
    for entry in result['rounds']:
        model = LiftedModel.load(entry['model'])
        error = multistep_errors(model.predict(data.x[:, 0], data.u), data.x)
        reported = entry['held_out_error']['summed_mse']
        assert reported == pytest.approx(error['summed_mse'], rel=1e-9)
    # Which law flew is read back from the bags: the fallback's share of the steps.
    evaluated = sorted((work / 'bags' / 'round1_eval').iterdir())
    loops = [read_loop(str(bag)) for bag in evaluated]
    share = sum(r.fallback_steps for r in loops) / sum(len(r.u) for r in loops)
    assert result['rounds'][1]['fallback_share'] == pytest.approx(share)
    assert f"| {100 * share:.0f}% |" in report.splitlines()[-1]
