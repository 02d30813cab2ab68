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


def test_evaluate_writes_its_table_and_plot_into_the_page(tiny_model, tmp_path):
    """With --page the page shows the run's own table between the markers named after --out,
    and the plot lands beside the page where the page links it."""
    page = tmp_path / 'docs' / 'learning.md'
    page.parent.mkdir()
    page.write_text('before\n<!-- eval:begin -->\nstale\n<!-- eval:end -->\nafter\n')
    out = tmp_path / 'eval'
    assert evaluate.main(['--model', str(tiny_model[0]), '--out', str(out), '--no-sindy',
                          '--test-trajectories', '50', '--page', str(page)]) == 0
    text = page.read_text()
    results = json.loads((out / 'comparison.json').read_text())
    table = text[text.index('<!-- eval:begin -->'):text.index('<!-- eval:end -->')]
    assert 'stale' not in table and text.startswith('before\n') and text.endswith('after\n')
    for method, figures in results.items():
        assert f"| {method} | {figures['summed_mse']:.4g} |" in table
    plot = page.parent / 'figures' / 'eval.png'
    assert plot.read_bytes() == (out / 'error_vs_step.png').read_bytes()
    assert page.parent / evaluate.figure_name('eval') == plot


def test_evaluate_refuses_a_page_without_its_markers_before_any_work(tiny_model, tmp_path,
                                                                     capsys):
    page = tmp_path / 'learning.md'
    page.write_text('no markers here\n')
    out = tmp_path / 'eval'
    assert evaluate.main(['--model', str(tiny_model[0]), '--out', str(out),
                          '--page', str(page)]) == 2
    assert not out.exists()
    error = capsys.readouterr().err.strip()
    assert error.startswith('evaluate: ') and '<!-- eval:begin -->' in error
    assert len(error.splitlines()) == 1
