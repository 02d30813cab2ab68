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
    assert loop.main(['--plant', 'actuator_weak', '--rounds', '1', '--steps', '300',
                      '--epochs', '1', '--out', str(tmp_path), '--namespace', ros_namespace]) == 0
    work = tmp_path / 'actuator_weak'
    result = json.loads((work / 'report.json').read_text())
    assert [r['round'] for r in result['rounds']] == [0, 1]
    assert (work / 'rounds.png').stat().st_size > 0
    assert '| 1 | `round1` |' in (work / 'report.md').read_text()

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
