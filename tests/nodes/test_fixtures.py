"""The fixtures users import (`tsr_koopman_ctrl.testing`), as a user's test suite uses them."""

import subprocess
import textwrap

import pytest

pytestmark = pytest.mark.ros
pytest_plugins = ['pytester']


def test_a_loop_in_a_namespace_of_its_own_runs_and_reads_back(tsr_loop):
    loop = tsr_loop(law='linear_lqr', steps=120)
    loop.wait_for_step(50, timeout=90.0)
    run = loop.finish()
    assert run.loop.namespace == loop.deployment.namespace != '/'
    assert run.loop.step.tolist() == list(range(121))
    assert run.figures['controller'] == 'linear_lqr' and not run.halted


def test_a_failing_test_still_stops_its_nodes(pytester, ros_domain):
    """A user's test that fails while its loop runs: the fixture stops the three processes."""
    pytester.makeconftest("pytest_plugins = ['tsr_koopman_ctrl.testing']\n")
    pytester.makepyfile(textwrap.dedent('''
        def test_fails_mid_run(tsr_loop):
            loop = tsr_loop(law='linear_lqr', steps=100000, namespace='/teardown_check')
            loop.wait_for_step(11, timeout=90.0)
            assert False, 'the test fails here'
    '''))
    result = pytester.runpytest_subprocess('-p', 'no:cacheprovider')
    result.assert_outcomes(failed=1)
    left = subprocess.run(['pgrep', '-f', '__ns:=/teardown_check'], capture_output=True,
                          text=True)
    assert left.stdout == '', 'processes left running: ' + left.stdout
