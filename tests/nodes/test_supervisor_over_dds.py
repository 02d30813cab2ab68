"""Which law flew each step, and why, as a deployment over DDS records it: the supervisor's
`flying` and `monitor` go out on ControllerStatus and come back from the bag (`read_loop`)."""

import itertools
import re

from conftest import ROOT
import numpy as np
import pytest

from tsr_koopman_ctrl.control.supervisor import FALLBACK, LEARNED, REASONS

pytestmark = pytest.mark.ros


def documented_takeback_steps():
    page = (ROOT / 'docs' / 'supervisor.md').read_text()
    return int(re.search(r'`takeback_steps` \((\d+)\)', page).group(1))


def test_the_bag_gives_the_law_that_flew_each_step_and_the_monitor_s_reason(tsr_loop):
    """The learned NMPC from the paper's start, its one-step prediction allowed to miss by
    0.03 (ROS-free, the default 0.2 never distrusts it there; 0.03 does, on its second step
    and again some 50 steps later). Every step of the bag names the law that flew; the
    learned law flies only trusted, each hand-over to the fallback gives its reason, and each
    take-back comes after the documented takeback_steps trusted steps in a row (the last of
    them flown by the learned law); the controller's last status counts the switches the
    bag shows."""
    steps, takeback = 120, documented_takeback_steps()
    run = tsr_loop(law='koopman_nmpc', steps=steps,
                   settings={'supervisor': {'prediction_threshold': 0.03}}).finish()
    flying, monitor = list(run.loop.flying[:steps]), list(run.loop.monitor[:steps])
    assert set(flying) == {LEARNED, FALLBACK} and flying[0] == LEARNED
    assert set(monitor) <= {'', *REASONS} and 'prediction' in monitor
    assert all(why == '' for law, why in zip(flying, monitor) if law == LEARNED)
    switches = [k for k in range(1, steps) if flying[k] != flying[k - 1]]
    handed_over = [k for k in switches if flying[k] == FALLBACK]
    taken_back = [k for k in switches if flying[k] == LEARNED]
    assert handed_over and taken_back
    assert all(monitor[k] in REASONS for k in handed_over)
    for k in taken_back:
        before = list(zip(flying, monitor))[:k]
        trusted = len(list(itertools.takewhile(lambda step: step == (FALLBACK, ''),
                                               reversed(before))))
        assert trusted == takeback - 1, (k, list(zip(flying, monitor))[max(0, k - takeback):k])
    assert run.figures['supervisor_switches'] == len(switches)
    assert run.figures['fallback_steps'] == flying.count(FALLBACK) == np.count_nonzero(
        run.loop.flying == FALLBACK)
