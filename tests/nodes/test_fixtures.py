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


@pytest.mark.parametrize('ending', ['fails', 'times_out'])
def test_a_failing_or_timed_out_test_still_stops_its_nodes(pytester, ending):
    """A user's test that fails, or runs past its time limit (pytest-timeout), while its loop
    runs: the fixtures stop the three processes, and nothing of the test is left running."""
    pytester.makeconftest("pytest_plugins = ['tsr_koopman_ctrl.testing']\n")
    namespace = f'/teardown_check_{ending}'
    pytester.makepyfile(textwrap.dedent(f'''
        import time

        import pytest


        @pytest.mark.timeout(60)
        def test_fails_mid_run(tsr_loop):
            loop = tsr_loop(law='linear_lqr', steps=100000, namespace='{namespace}')
            loop.wait_for_step(11, timeout=90.0)
            assert False, 'the test fails here'


        @pytest.mark.timeout(20)
        def test_times_out_mid_run(tsr_loop):
            loop = tsr_loop(law='linear_lqr', steps=100000, namespace='{namespace}')
            loop.wait_for_step(11, timeout=90.0)
            time.sleep(1000)
    '''))
    selected = {'fails': 'test_fails_mid_run', 'times_out': 'test_times_out_mid_run'}[ending]
    result = pytester.runpytest_subprocess('-p', 'no:cacheprovider', '-k', selected)
    result.assert_outcomes(failed=1)
    if ending == 'times_out':
        result.stdout.fnmatch_lines(['*Timeout*'])
    left = subprocess.run(['pgrep', '-f', f'__ns:={namespace}'], capture_output=True,
                          text=True)
    assert left.stdout == '', 'processes left running: ' + left.stdout


@pytest.mark.timeout(120)
def test_a_user_suite_with_the_plugin_knows_the_ros_marker(pytester):
    """A suite of a user's own that loads the plugin and marks its tests `ros` gets no
    unknown-marker warning (here an error) and can deselect them with -m "not ros"."""
    pytester.makeconftest("pytest_plugins = ['tsr_koopman_ctrl.testing']\n")
    pytester.makepyfile(textwrap.dedent('''
        import pytest


        @pytest.mark.ros
        def test_marked():
            pass


        def test_plain():
            pass
    '''))
    result = pytester.runpytest_subprocess('-p', 'no:cacheprovider', '-W',
                                           'error::pytest.PytestUnknownMarkWarning',
                                           '-m', 'not ros')
    result.assert_outcomes(passed=1, deselected=1)


def test_a_test_has_a_domain_and_a_namespace_of_its_own(ros, ros_domain, ros_namespace,
                                                        start_node):
    """The domain is reserved for the test (no other draw gets it while it runs), and the
    nodes it starts, its client's among them, live in its namespace, not the root one."""
    from tsr_koopman_ctrl.launcher import domain_in_use, reserve_domain
    with pytest.raises(RuntimeError, match='no free DDS domain'):
        reserve_domain(candidates=[ros_domain])
    assert ros_namespace.startswith('/t_test_a_test_has_a_domain')
    assert ros.node.get_namespace() == ros_namespace and domain_in_use(ros_domain)
    start_node('tsr_sim', 'sim_node', 'tsr_sim', {'progress_every': 0})
    ros.spin_until(lambda: ('tsr_sim', ros_namespace) in
                   ros.node.get_node_names_and_namespaces(), timeout=30.0,
                   what='the simulator in the test\'s namespace')
    assert all(namespace == ros_namespace for _, namespace in
               ros.node.get_node_names_and_namespaces())
