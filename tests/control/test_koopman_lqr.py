"""The paper's Koopman-LQR on the shipped koopman_block model deploys the tether."""

import numpy as np
import pytest
from tsr_sim import dynamics

from tsr_koopman_ctrl.control import closed_loop, KoopmanLqr, make_controller, ObserverSettings
from tsr_koopman_ctrl.control.koopman_lqr import KoopmanLqrSettings
from tsr_koopman_ctrl.control.registry import preset
from tsr_koopman_ctrl.evaluation import (closed_loop_figures, COMPARISON_STARTS,
                                         HELD_OUT_STARTS, PAPER_START, run_figures, settle_index)

BARE = ObserverSettings(disturbance='none')
#: The paper's own cost (Q' = I, R' = 15): config/untuned.yaml.
PAPER_COST = {'state_weight': 'lifted', 'r': 15.0}


def deploy(controller, x0, steps=2000):
    states, u = closed_loop(controller, x0, steps)
    assert len(states) == steps + 1, 'the state left the domain'
    return run_figures(np.arange(steps + 1) * dynamics.PAPER_STEP, states, u), u


@pytest.fixture(scope='module')
def law():
    return KoopmanLqr()   # the defaults: the shipped koopman_block_fast, the tuned cost


def test_the_default_is_the_fast_block_model_and_its_gain_stabilises_it(law):
    assert law.settings.model == 'koopman_block_fast'
    assert law.closed_loop_spectral_radius() < 1.0


def test_only_the_state_block_has_unstable_modes(law):
    """The observables are stable by construction: every |eig A| >= 1 is an eigenvalue of the
    model's own linearisation at the target, the largest near the plant's 1.0128 per step."""
    values = np.linalg.eigvals(law.model.A)
    local = np.linalg.eigvals(law.model.local_linear_model()[0])
    unstable = values[np.abs(values) >= 1.0]
    assert unstable.size and all(np.min(np.abs(local - v)) < 1e-4 for v in unstable)
    assert np.abs(values).max() == pytest.approx(1.0128, abs=2e-3)


@pytest.mark.parametrize('observer', [BARE, None], ids=['bare', 'offset-free'])
@pytest.mark.parametrize('x0', COMPARISON_STARTS + HELD_OUT_STARTS)
def test_koopman_lqr_deploys_into_the_one_percent_zone(x0, observer):
    figures, u = deploy(make_controller('koopman_lqr', observer=observer), x0)
    assert figures['settle_tau'] is not None and figures['settle_tau'] < 6.5, figures
    assert figures['swing'] < 0.8
    assert np.all((u >= 0.0) & (u <= 5.0))


@pytest.mark.parametrize('x0', COMPARISON_STARTS)
def test_the_papers_own_cost_deploys_too(x0):
    figures, u = deploy(KoopmanLqr(**PAPER_COST), x0)
    assert figures['settle_tau'] is not None and figures['settle_tau'] < 6.5, figures
    assert np.all((u >= 0.0) & (u <= 5.0))


@pytest.mark.parametrize('x0', COMPARISON_STARTS[:2])
def test_the_dense_default_model_does_not_deploy(x0):
    """Why koopman_lqr has a model of its own: on koopman_default it never settles."""
    states, _ = closed_loop(KoopmanLqr(model='koopman_default', **PAPER_COST), x0, 2000)
    assert len(states) < 2001 or settle_index(states) is None


def preset_settings(name):
    """The law's settings in a preset file (config/<name>.yaml), as `compare --presets` takes
    them."""
    return preset(name)['koopman_lqr']


def test_koopman_block_fast_observables_decay_within_0_95_per_step():
    """Every |eig A| beyond 0.95 is one of the state block's (the model's own linearisation)."""
    law = KoopmanLqr(**preset_settings('tuned_cross'))
    assert law.settings.model == 'koopman_block_fast'
    values = np.linalg.eigvals(law.model.A)
    local = np.linalg.eigvals(law.model.local_linear_model()[0])
    slow = values[np.abs(values) > 0.95]
    assert slow.size == 4 and all(np.min(np.abs(local - v)) < 1e-4 for v in slow)


@pytest.mark.parametrize('name, bound', [('tuned_cross', 1.35), ('defaults', 1.4)])
@pytest.mark.parametrize('x0', COMPARISON_STARTS + HELD_OUT_STARTS)
def test_on_koopman_block_fast_the_tuned_settings_settle_near_the_frontier(x0, name, bound):
    """Issue 14's bound for the paper's law is 1.6x. The cross-tuned preset and the defaults
    (tuned for the ratio) plan on koopman_block_fast; measured 1.25..1.32x cross-tuned,
    1.27..1.36x ratio-tuned (diagonal Q; on koopman_block that search reached 1.36..1.77x)."""
    settings = ({'model': KoopmanLqrSettings().model} if name == 'defaults'
                else preset_settings(name))
    assert settings['model'] == 'koopman_block_fast'
    figures = closed_loop_figures(make_controller('koopman_lqr', **settings), x0, 1500)
    assert figures['frontier_ratio'] is not None and figures['frontier_ratio'] < bound, figures
    assert figures['swing'] < 0.8


def test_the_observable_feedforward_is_what_makes_it_fast():
    """The same law with K_phi = 0 (the LQR of the model's state block alone, the same gain
    near the target) settles ~1 tau later from the paper's start (4.69 against 5.64 tau)."""
    controller = make_controller('koopman_lqr', supervisor='none', safety='none',
                                 **preset_settings('tuned_cross'))
    with_lift = closed_loop_figures(controller, PAPER_START, 1500)['settle_tau']
    law = controller.law
    state_gain, observable_gain = law.observable_feedforward_split()
    assert np.abs(observable_gain).max() > 0.0
    law.gain = np.concatenate([state_gain, np.zeros_like(observable_gain)])
    controller.reset()
    without = closed_loop_figures(controller, PAPER_START, 1500)['settle_tau']
    assert with_lift < 4.8 and without > with_lift + 0.5
