"""The mpc_sweep command against loops closed by hand."""

import json

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import closed_loop, KoopmanMpc
from tsr_koopman_ctrl.evaluation import COMPARISON_STARTS
from lab import mpc_sweep

from conftest import SHIPPED_MODEL


def test_mpc_sweep_runs_each_model_and_horizon_from_every_start(tmp_path, capsys):
    out = tmp_path / 'sweep'
    assert mpc_sweep.main(['--models', SHIPPED_MODEL, '--horizons', '5', '8', '--steps', '300',
                           '--out', str(out)]) == 0
    results = json.loads((out / 'mpc_sweep.json').read_text())
    assert [r['horizon'] for r in results] == [5, 8]
    assert all(len(r['runs']) == len(COMPARISON_STARTS) for r in results)
    for r in results:   # the paper's start, against a loop closed here
        states, _ = closed_loop(KoopmanMpc(model=SHIPPED_MODEL, horizon=r['horizon']),
                                dynamics.PAPER_INITIAL_STATE, 300)
        np.testing.assert_allclose(r['runs'][0]['final_state'], states[-1], atol=1e-12)
    assert '| 5 |' in (out / 'mpc_sweep.md').read_text()
    assert mpc_sweep.main(['--models', str(tmp_path / 'none'), '--out', str(out)]) == 2
    assert 'none: no such model directory' in capsys.readouterr().err
