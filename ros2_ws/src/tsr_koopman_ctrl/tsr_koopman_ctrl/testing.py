"""pytest fixtures for rclpy integration tests against the nodes, for your own test suites.

    # conftest.py
    pytest_plugins = ['tsr_koopman_ctrl.testing']

    # test_my_controller.py
    def test_the_loop_reaches_step_100(tsr_loop):
        loop = tsr_loop(law='linear_lqr', steps=300)     # sim, controller, recorder
        loop.ros.spin_until(lambda: loop.status and loop.status.step >= 100, timeout=60)
        run = loop.finish()                             # waits for the end, reads the bag
        assert run.figures['settle_tau'] is not None

Fixtures (each test gets a DDS domain and a ROS namespace of its own, and everything it starts
is stopped at teardown, also when the test fails):
  ros_domain    the test's ROS_DOMAIN_ID: one that no other process on the host uses,
                reserved for the test (`launcher.reserve_domain`; TSR_TEST_DOMAIN=N pins
                every test to N, unchecked, to watch a test with a ROS tool)
  ros_namespace the test's ROS namespace ('/t_' and the test's name): where `start_node`
                and `tsr_loop` put their nodes and the `ros` client's node lives, so that
                relative names ('tsr/reset', 'tsr_controller/get_parameters') resolve alike
  ros           a `RosClient`: an rclpy node in this process on that domain and in that
                namespace (spin_until, spin_for, call a service, get and set a node's
                parameters)
  start_node    start_node(package, executable, name, params, namespace=...) -> NodeProcess:
                an installed node as its own process (in the test's namespace unless one is
                given; '/' for the root namespace), its log in the test's tmp_path
  tsr_loop      tsr_loop(law=..., steps=..., namespace=..., **Deployment options) -> a
                running loop (`deployment.Deployment`, the first in the test's namespace)
                whose simulator status the `ros` client follows; .finish() waits for the end
                and returns the RunResult read from the bag

Tests that use them start processes: mark them `@pytest.mark.ros` (the plugin declares the
marker, so a suite of your own needs no pytest.ini entry for it; `-m "not ros"` deselects them).
"""

import os
import re
import time

import pytest

from tsr_koopman_ctrl.launcher import NodeProcess, reserve_domain

#: The marker of tests that start ROS processes, declared for every suite using the plugin.
ROS_MARKER = 'ros: starts ROS processes over DDS (deselect with -m "not ros")'


def pytest_configure(config):
    config.addinivalue_line('markers', ROS_MARKER)


class RosClient:
    """An rclpy node in the test process, on the test's domain (its own rclpy context), in
    `namespace` (relative names it uses resolve there)."""

    def __init__(self, domain, namespace=None):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.namespace = namespace or '/'
        self.node = rclpy.create_node('test_client', namespace=self.namespace,
                                      context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate, timeout=10.0, what='condition'):
        """Spin until `predicate()` is true; TimeoutError naming `what` after `timeout` s."""
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise TimeoutError(f'timed out after {timeout} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.05)

    def spin_for(self, seconds, until=None):
        """Spin for `seconds`, or less if `until()` becomes true."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not (until and until()):
            self.executor.spin_once(timeout_sec=0.05)

    def call(self, service_type, name, request, timeout=10.0, resend=None):
        """Call a service and wait for its response. `resend`: for a read-only service, send
        the request again every `resend` s without a response (a service just discovered may
        not yet hear its first requests; a transition must not be sent twice)."""
        client = self.node.create_client(service_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                raise TimeoutError(f'no service {name} after {timeout} s')
            deadline = time.monotonic() + timeout
            futures = [client.call_async(request)]
            while not any(f.done() for f in futures):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f'timed out after {timeout} s waiting for the response '
                                       f'of {name}')
                self.spin_for(min(left, resend or left),
                              until=lambda: any(f.done() for f in futures))
                if resend and not any(f.done() for f in futures):
                    futures.append(client.call_async(request))
            return next(f for f in futures if f.done()).result()
        finally:
            self.node.destroy_client(client)

    def set_parameters(self, node_name, values, timeout=10.0):
        """Set parameters of a running node: [(successful, reason)] in the order given."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        request = SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        response = self.call(SetParameters, f'{node_name}/set_parameters', request, timeout)
        return [(r.successful, r.reason) for r in response.results]

    def get_parameters(self, node_name, names, timeout=10.0):
        """{name: value} of a running node's parameters."""
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python
        response = self.call(GetParameters, f'{node_name}/get_parameters',
                             GetParameters.Request(names=list(names)), timeout, resend=2.0)
        return {name: parameter_value_to_python(value)
                for name, value in zip(names, response.values)}

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


class RunningLoop:
    """A deployment started by the `tsr_loop` fixture: `status` is the simulator's last
    tsr_msgs/SimStatus seen by `ros`; `finish()` waits for the run and reads its bag."""

    def __init__(self, deployment, ros):
        from tsr_msgs.msg import SimStatus
        from tsr_sim import ros_io, wire
        self.deployment, self.ros, self.status = deployment, ros, None
        ros.node.create_subscription(
            SimStatus, wire.resolve(wire.SIM_STATUS_TOPIC, deployment.namespace or '/'),
            lambda msg: setattr(self, 'status', msg), ros_io.LATCHED_QOS)

    def wait_for_step(self, step, timeout=60.0):
        """Spin until the simulator reports `step`, or has finished a run that long (a fast
        loop can end, and its latched status leave with the process, before this reader has
        matched); TimeoutError with each node's last log lines (what the loop was waiting
        for) after `timeout` s."""
        sim = self.deployment.processes[-1]

        def reached():
            if self.status is not None and self.status.step >= step:
                return True
            return (self.deployment.steps >= step and not sim.running()
                    and sim.process.returncode == 0)
        try:
            self.ros.spin_until(reached, timeout=timeout, what=f'step {step} of the loop')
        except TimeoutError as error:
            seen = ('no status' if self.status is None
                    else f'last status at step {self.status.step}')
            tails = ''.join(f'\n--- {p.name} ({"running" if p.running() else "exited"}):\n'
                            f'{p.log_tail().rstrip()}' for p in self.deployment.processes)
            raise TimeoutError(f'{error} ({seen}){tails}') from None

    def finish(self):
        self.deployment.wait()
        self.deployment.stop()
        return self.deployment.result()


@pytest.fixture
def ros_domain():
    """The test's DDS domain: one no other process on the host uses (`reserve_domain`: no
    bound port of the domain, no lock of another of this project's processes, not the
    caller's ROS_DOMAIN_ID), reserved until the test's teardown is over. TSR_TEST_DOMAIN pins
    every test to one domain, unchecked (to watch a test from a ROS tool on that domain)."""
    if os.environ.get('TSR_TEST_DOMAIN'):
        yield int(os.environ['TSR_TEST_DOMAIN'])
        return
    with reserve_domain() as reservation:
        yield reservation.id


@pytest.fixture
def ros_namespace(request):
    """The test's ROS namespace: '/t_' and the test's name, as a ROS name allows it."""
    name = re.sub(r'[^0-9a-zA-Z]+', '_', request.node.name).strip('_').lower()
    return '/t_' + name[:60].rstrip('_')


@pytest.fixture
def ros(ros_domain, ros_namespace):
    client = RosClient(ros_domain, ros_namespace)
    yield client
    client.close()


@pytest.fixture
def start_node(ros_domain, ros_namespace, tmp_path):
    """Factory: start_node(package, executable, name, params, ...) -> NodeProcess, in the
    test's namespace unless `namespace` is given ('/': the root namespace); all stopped at
    teardown (SIGINT, SIGKILL after a grace period). Logs go to tmp_path/<name>.log."""
    started = []

    def start(package, exe, name, params=None, extra_args=(), namespace=None, cwd=None):
        process = NodeProcess(package, exe, name, params, domain_id=ros_domain,
                              log_path=str(tmp_path / f'{name}.log'), extra_args=extra_args,
                              namespace=namespace or ros_namespace, cwd=cwd)
        started.append(process)
        return process

    yield start
    stop_all(started)


def stop_all(processes):
    """Stop every process, each even if stopping another raised; the first error after."""
    errors = []
    for process in processes:
        try:
            process.stop()
        except BaseException as error:      # a KeyboardInterrupt too: the others still stop
            errors.append(error)
    if errors:
        raise errors[0]


@pytest.fixture
def tsr_loop(ros_domain, ros_namespace, ros, tmp_path):
    """Factory: tsr_loop(law=..., steps=..., **options) -> RunningLoop, the three nodes
    started (`deployment.Deployment` options; bags and logs in tmp_path; the first loop in the
    test's namespace, later ones in '<namespace>_1', ...); stopped at teardown."""
    from tsr_koopman_ctrl.deployment import Deployment
    loops = []

    def start(law='linear_lqr', steps=300, namespace=None, **options):
        namespace = namespace or (f'{ros_namespace}_{len(loops)}' if loops else ros_namespace)
        deployment = Deployment(law, steps=steps, namespace=namespace, domain=ros_domain,
                                bags=str(tmp_path / 'bags'), logs=str(tmp_path / 'logs'),
                                progress=False, **options)
        loops.append(deployment)
        running = RunningLoop(deployment, ros)
        deployment.start()
        return running

    yield start
    stop_all(loops)
