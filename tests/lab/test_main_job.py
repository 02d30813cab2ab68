"""`lab.main_job` (the README's headline) end to end on a short run: both laws deployed over
DDS, its table, its figures file and its plot written, and every figure its bag's."""

import json

import pytest

from lab import main_job
from tsr_koopman_ctrl.deployment import read_result, summary_table

pytestmark = pytest.mark.ros

STEPS = 300
#: The figures a row holds that a bag gives back (run_figures and the controller's counters).
FROM_THE_BAG = ('settle_tau', 'final_state', 'theta_min', 'theta_max', 'length_overshoot',
                'tension_max', 'tension_integral', 'steps', 'halted', 'compute_median_us',
                'compute_p99_us', 'solver_fallbacks', 'fallback_steps', 'frontier_tau')


def test_the_main_job_writes_its_table_and_plot_from_its_bags(tmp_path, capsys, ros_namespace):
    out = tmp_path / 'main_job'
    page = tmp_path / 'README.md'
    page.write_text('# A page\n<!-- main_job:begin -->\nold\n<!-- main_job:end -->\nafter\n')
    assert main_job.main(['--steps', str(STEPS), '--out', str(out), '--page', str(page),
                          '--namespace', ros_namespace]) == 0
    rows = json.loads((out / 'main_job.json').read_text())
    assert [row['controller'] for row in rows] == main_job.parser().get_default('law')
    assert (out / 'main_job.png').stat().st_size > 10_000
    recomputed = []
    for row in rows:
        assert row['bag'].startswith(str(out / 'bags'))
        again = read_result(row['bag'], row['controller'], row['x0'], STEPS,
                            ros_namespace).figures
        recomputed.append(again)
        assert row['steps'] == row['planned_steps'] == STEPS and not row['halted']
        for name in FROM_THE_BAG:        # JSON keeps a float to the last bit
            assert row[name] == again[name], (row['controller'], name)
    # The table is the bags' table, as printed.
    table = (out / 'main_job.md').read_text()
    assert table == summary_table(recomputed) + '\n'
    assert table.rstrip() in capsys.readouterr().out
    # The page shows the headline of the same runs, and the plot beside it.
    shown = page.read_text()
    assert 'old' not in shown and shown.endswith('<!-- main_job:end -->\nafter\n')
    assert main_job.headline(rows) in shown
    for row in rows:
        assert f"| `{row['controller']}`" in shown and f"{row['tension_max']:.2f}" in shown
    assert (tmp_path / main_job.FIGURE).read_bytes() == (out / 'main_job.png').read_bytes()


def test_the_main_job_refuses_a_page_without_its_markers_before_it_deploys(tmp_path, capsys):
    page = tmp_path / 'README.md'
    page.write_text('# no markers\n')
    assert main_job.main(['--out', str(tmp_path / 'main_job'), '--page', str(page)]) == 2
    assert 'has no <!-- main_job:begin -->' in capsys.readouterr().err
    assert not (tmp_path / 'main_job').exists()
