"""The evaluate command: deep model against the baselines."""

import json

import pytest

from lab import prediction as evaluate

from tsr_koopman_ctrl.learning import dataset as datasets
from tsr_koopman_ctrl.learning import errors
from tsr_koopman_ctrl.model import lifted


def test_evaluate_command_writes_the_comparison(tiny_model, tmp_path):
    out = tmp_path / 'eval'
    assert evaluate.main(['--model', str(tiny_model[0]), '--out', str(out), '--no-sindy',
                          '--test-trajectories', '200']) == 0
    results = json.loads((out / 'comparison.json').read_text())
    assert set(results) == {'deep_koopman', 'edmd', 'edmd_stabilised'}
    # Re-sampled training data and the numpy model reproduce the deep model's own figure.
    model = lifted.LiftedModel.load(tiny_model[0])
    test, _ = datasets.sample(datasets.SamplingConfig(trajectories=200, seed=datasets.TEST_SEED))
    own = errors.multistep_errors(model.predict(test.x[:, 0], test.u), test.x)
    assert results['deep_koopman']['summed_mse'] == pytest.approx(own['summed_mse'])
    assert '| edmd_stabilised |' in (out / 'comparison.md').read_text()
    assert (out / 'error_vs_step.png').stat().st_size > 10_000
