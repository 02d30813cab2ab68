"""The comparison's bar chart of frontier ratios."""

import matplotlib.image

from tsr_koopman_ctrl.evaluation.plots import plot_ratios


def test_the_ratio_chart_draws_every_run_and_a_run_that_did_not_settle(tmp_path):
    rows = [{'law': law, 'preset': preset, 'start': start, 'starts': kind, 'frontier_ratio': v}
            for law, preset, v0 in (('linear_lqr', 'tuned', 1.4), ('koopman_mpc', 'tuned', None),
                                    ('koopman_mpc', 'tuned_settle', 1.35))
            for start, kind, v in (([0.0, 0.0, -0.99, 0.5], 'comparison', v0),
                                   ([0.1, -0.1, -0.9, 0.5], 'held-out', 1.3))]
    path = tmp_path / 'ratios.png'
    plot_ratios(rows, path)
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[1] > image.shape[0] > 100
