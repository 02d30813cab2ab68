"""physics_nmpc: the nonlinear MPC on the exact model, deployed in the ROS-free loop.

The closed loops are shortened to what the assertions need (~20 ms a step): 5 tau with the
default swing bound 0.8 rad, 10 tau with 0.4. Both use one NLP (the bound is a parameter of
its constraints), compiled once per machine (about two minutes; cached under
~/.cache/tsr_koopman_ctrl).
"""

import warnings

import numpy as np
import pytest
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import closed_loop, make_controller, OffsetFree
from tsr_koopman_ctrl.control import physics_nmpc
from tsr_koopman_ctrl.control.physics_nmpc import PhysicsNmpc
from tsr_koopman_ctrl.evaluation import frontier_tau, PAPER_START, run_figures

#: Minimum-time deployment from the paper's start with 0 <= u <= 5 (docs/frontier.md), with
#: |theta| <= 0.8 and with |theta| <= 0.4.
FRONTIER_SWING_08 = frontier_tau(PAPER_START, 0.8)
FRONTIER_SWING_04 = frontier_tau(PAPER_START, 0.4)


def figures(states, u):
    return run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, u)


@pytest.fixture(scope='module')
def free_law():
    return PhysicsNmpc()   # defaults: |theta| <= 0.8


def test_nmpc_deploys_at_the_minimum_time_frontier(free_law):
    states, u = closed_loop(free_law, PAPER_START, 500)
    summary = figures(states, u)
    assert summary['settle_tau'] is not None
    assert summary['swing'] <= 0.8
    assert summary['settle_tau'] <= 1.1 * FRONTIER_SWING_08   # measured 3.55 (1.075x)
    assert np.all((u >= 0.0) & (u <= 5.0))
    assert free_law.fallbacks == 0 and free_law.compiled


def test_swing_bound_holds_on_the_plant_and_the_deployment_settles():
    law = PhysicsNmpc(theta_max=0.4)
    states, u = closed_loop(law, PAPER_START, 1000)
    summary = figures(states, u)
    assert summary['swing'] <= 0.4
    assert summary['settle_tau'] is not None
    assert summary['settle_tau'] <= 1.1 * FRONTIER_SWING_04   # measured 9.1
    assert np.all((u >= 0.0) & (u <= 5.0)) and law.fallbacks == 0


def test_failed_solves_fly_the_previous_plan_and_are_counted(free_law, monkeypatch):
    free_law.reset()
    x = np.array(PAPER_START)
    free_law.compute(x)
    expected = float(free_law.shifted_plan(free_law.h)[0])
    monkeypatch.setattr(free_law, 'solve', lambda *args: ({}, False))
    assert free_law.compute(x) == expected
    assert free_law.fallbacks == 1 and free_law.cold_solves == 2
    # With no plan yet: the linearised LQR law's move (Q = I, R = 1), clamped.
    free_law.reset()
    x = np.array([0.02, 0.0, -0.05, 0.0])
    assert free_law.compute(x) == pytest.approx(
        min(max(3.0 - float(free_law.lqr_gain @ x), 0.0), 5.0))
    assert free_law.fallbacks == 1


def test_offset_free_wrapper_flies_it(free_law):
    law = OffsetFree(free_law)
    states, u = closed_loop(law, PAPER_START, 20)
    assert len(u) == 20 and np.all((u >= 0.0) & (u <= 5.0)) and law.fallbacks == 0


def test_without_a_compiler_cache_it_warns_once_and_solves_interpreted(tmp_path, monkeypatch):
    blocker = tmp_path / 'file'
    blocker.write_text('')
    monkeypatch.setenv('TSR_NMPC_CACHE', str(blocker / 'cache'))   # cannot be created
    monkeypatch.setattr(physics_nmpc, '_warned', [])
    with pytest.warns(RuntimeWarning, match='interpreted'):
        law = PhysicsNmpc(horizon=1.0, interval=0.3)
    assert not law.compiled
    assert 0.0 <= law.compute(np.array(PAPER_START)) <= 5.0 and law.fallbacks == 0
    with warnings.catch_warnings():
        warnings.simplefilter('error')                  # a second law: no second warning
        assert not PhysicsNmpc(horizon=1.0, interval=0.3).compiled


@pytest.mark.parametrize('overrides, message', [
    ({'horizon': 0.0}, 'physics_nmpc.horizon must be >= 0.2, got 0.0'),
    ({'q': (1.0, 1.0)}, 'physics_nmpc.q needs 4 numbers'),
    ({'theta_max': 0.0}, 'physics_nmpc.theta_max must be >= 0.01'),
    ({'r': float('inf')}, 'physics_nmpc.r must be finite'),
    ({'horizon': 0.5, 'h': 0.1}, 'physics_nmpc.horizon must exceed the lead intervals')])
def test_bad_settings_are_one_line(overrides, message):
    with pytest.raises(ValueError, match=message.replace('(', r'\(')) as error:
        make_controller('physics_nmpc', **overrides)
    assert '\n' not in str(error.value)
