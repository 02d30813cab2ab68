"""The ROS-free rehearsal of the timed loop (`lab.timed_rehearsal`): with an instant law it is
the lockstep loop (`closed_loop`, sample for sample), and a law slower than the period sees
only the newest state, is told how many samples passed, and its command reaches the plant
when its compute ends."""

import numpy as np
import pytest

from lab.timed_rehearsal import main, timed_loop
from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.control.law import Law
from tsr_koopman_ctrl.evaluation import PAPER_START


def test_an_instant_law_flies_the_lockstep_loop():
    law = make_controller('koopman_lqr')
    states, figures = timed_loop(law, PAPER_START, 300, compute_periods=lambda result: 0.0)
    expected, _ = closed_loop(make_controller('koopman_lqr'), PAPER_START, 300)
    np.testing.assert_array_equal(states, expected)
    assert figures == {'dropped': 0, 'overruns': 0, 'longest': 0.0, 'lost': False}


class Recorder(Law):
    """Flies the number of states it has seen as a tension; records what it was told."""

    name = 'recorder'

    def __init__(self):
        super().__init__()
        self.seen, self.elapsed_told = [], []

    def compute(self, x):
        self.seen.append(np.asarray(x, dtype=float).copy())
        return float(len(self.seen) % 5)

    def elapsed(self, steps):
        self.elapsed_told.append(steps)


def test_a_law_slower_than_the_period_answers_the_newest_state_late():
    """Computes of 2.4 periods: after the first (which starts the clock) the law answers the
    newest state when it is done (1, then 3 at 3.4, 5 at 5.8, 8 at 8.2, 10 at 10.6), is told
    how many samples passed, and its command for a state flies from the first tick after its
    compute ends (sample s is advanced at tick s + 1)."""
    law = Recorder()
    start = (0.0, 0.0, -0.5, 0.0)
    states, figures = timed_loop(law, start, 30, compute_periods=lambda result: 2.4)
    answered = [k for k in range(len(states)) if any(
        np.allclose(states[k], seen, rtol=0, atol=1e-12) for seen in law.seen)]
    assert answered[:6] == [0, 1, 3, 5, 8, 10]
    assert law.elapsed_told[:4] == [2, 2, 3, 2]
    assert figures['dropped'] == sum(steps - 1 for steps in law.elapsed_told)
    assert figures['overruns'] == len(law.seen) - 1 and figures['longest'] == 2.4
    # the lockstep plant under the tensions the law's commands set, from the samples they
    # reached it: the same states
    expected, _ = closed_loop(ScheduleLaw({0: 1.0, 3: 2.0, 5: 3.0, 8: 4.0}), start, 10)
    np.testing.assert_allclose(states[:11], expected, rtol=0, atol=1e-12)


class ScheduleLaw(Law):
    """Flies the tension `schedule` gives from each sample on (a lockstep reference)."""

    name = 'schedule'

    def __init__(self, schedule):
        super().__init__()
        self.schedule, self.k, self.u = schedule, 0, None

    def compute(self, x):
        self.u = self.schedule.get(self.k, self.u)
        self.k += 1
        return self.u


@pytest.mark.timeout(600)
def test_the_study_writes_its_table(tmp_path):
    page = tmp_path / 'page.md'
    page.write_text('<!-- timed_rehearsal:begin -->\n<!-- timed_rehearsal:end -->\n')
    out = tmp_path / 'timed_rehearsal'        # (the markers are named after it)
    assert main(['--slowdown', '1', '--steps', '50', '--law', 'koopman_lqr', '--out',
                 str(out), '--page', str(page)]) == 0
    text = page.read_text()
    assert text.count('| [') == 9 and 'compute x1' in text
    assert (out / 'timed_rehearsal.json').exists()


def test_the_summary_counts_the_runs_lost_where_the_verified_law_alone_holds():
    """Under a bound a run is lost out of the domain or past the bound's tolerance; a start
    the verified law loses too is not counted against the law."""
    from lab.timed_rehearsal import summary

    def row(start, lost=False, swing=0.39, longest=0.5):
        return {'start': list(start), 'slowdown': 1.0, 'lost': lost, 'swing': swing,
                'longest': longest}
    a, b, c = (0.0, 0.0, -0.99, 0.5), (0.1, 0.0, -0.9, 0.3), (0.2, 0.0, -0.9, 0.3)
    rows = [row(a, swing=0.41, longest=1.4), row(b, lost=True), row(c)]
    reference = [row(a), row(b, lost=True), row(c)]
    line, = summary(rows, reference, [1.0], 'physics_nmpc', 0.405)
    assert line == ('- compute x1: 2 of 3 runs lost (past 0.405 rad or out of the domain); '
                    'longest step 1.4 periods; lost where `physics_nmpc` alone holds (2 runs):'
                    ' 1 ([0.0, 0.0, -0.99, 0.5])')
    unbounded, = summary(rows, [], [1.0], None, None)
    assert unbounded == '- compute x1: 1 of 3 runs lost; longest step 1.4 periods'
