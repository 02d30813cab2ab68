"""docs/new_law.md's example law, taken from the page's code blocks: it flies through
`closed_loop` and, once registered, the registry, the node's sections and parameter file,
deploy's --set, the comparison and the tuner pick it up as the page says."""

import re
import types

import numpy as np
import pytest
from tsr_sim import dynamics

from conftest import ROOT
from tsr_koopman_ctrl.control import make_controller, OffsetFree, registry
from tsr_koopman_ctrl.evaluation import run_figures

PAGE = ROOT / 'docs' / 'new_law.md'
MARKER = '<!-- the example law: tests/control/test_new_law.py runs the code block below -->'


def page_blocks():
    """The page's python blocks from the example law's on: (the law's module, the use)."""
    text = PAGE.read_text()
    assert MARKER in text
    return re.findall(r'```python\n(.*?)```', text.split(MARKER, 1)[1], re.S)[:2]


@pytest.fixture
def example():
    """The example law's module, built from the page."""
    module = types.ModuleType('new_law_example')
    exec(compile(page_blocks()[0], str(PAGE), 'exec'), module.__dict__)
    return module


@pytest.fixture
def registered(example, monkeypatch):
    monkeypatch.setitem(registry.CONTROLLERS, 'fixed_gain', example.FixedGain)
    return example.FixedGain


def test_the_example_law_flies_the_paper_s_deployment_as_the_page_shows(example):
    use = dict(example.__dict__)
    exec(compile(page_blocks()[1], str(PAGE), 'exec'), use)
    states, tensions = use['states'], use['tensions']
    assert len(states) == 2001 and np.isfinite(states).all()
    assert 0.0 <= tensions.min() and tensions.max() <= dynamics.TENSION_LIMIT
    figures = run_figures(np.arange(len(states)) * dynamics.PAPER_STEP, states, tensions)
    # The untuned linear_lqr's gain: its ~9.1 tau (docs/paper_notes.md), not the tuned 4.9.
    assert figures['settle_tau'] is not None and 8.0 < figures['settle_tau'] < 10.0
    # The defaults are the linearised LQR's gain for Q = I, R = 1, rounded.
    from tsr_koopman_ctrl.control import LinearisedLqr
    np.testing.assert_allclose(example.FixedGain().settings.gain,
                               LinearisedLqr(q=(1.0,) * 4, r=1.0).gain, atol=1e-4)
    with pytest.raises(ValueError, match=r'fixed_gain.gain needs 4 numbers'):
        example.FixedGain(gain=(1.0, 2.0))


def test_once_registered_every_tool_picks_it_up(registered):
    from tsr_koopman_ctrl.commands.config import example_yaml
    from tsr_koopman_ctrl.control.registry import parse_assignments
    from tsr_koopman_ctrl.control.settings import unknown_setting_names
    from lab import compare
    from lab.tuning.space import tunable
    law = make_controller('fixed_gain')
    assert isinstance(law, OffsetFree) and isinstance(law.law, registered)
    assert type(make_controller('fixed_gain', observer='none')) is registered
    assert 'fixed_gain' in registry.settings_sections()
    assert unknown_setting_names(['fixed_gain.gian'], registry.settings_sections()) == [
        "parameter 'fixed_gain.gian': fixed_gain has no setting 'gian' (did you mean "
        "'fixed_gain.gain'?)"]
    assert '    fixed_gain:\n' in example_yaml() and \
        '      gain: [2.8716, -0.3923, -6.1623, -3.4286]\n' in example_yaml()
    assert parse_assignments(['fixed_gain.gain=3,-0.4,-6,-3.4']) == {
        'fixed_gain': {'gain': (3.0, -0.4, -6.0, -3.4)}}
    assert 'fixed_gain' in compare.parser().get_default('law')
    assert tunable('fixed_gain') == [('gain', registered.Settings().gain,
                                      (-10.0, 10.0, 'linear'))]
