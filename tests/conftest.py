"""Fixtures for rclpy integration tests: an isolated DDS domain, nodes as separate processes
(the installed executables) and an in-test rclpy node on the same domain."""

import os
import time

import pytest


@pytest.fixture(scope='session')
def domain_id():
    """A DDS domain of our own, so parallel runs and other ROS graphs do not interfere."""
    return int(os.environ.get('TSR_TEST_DOMAIN', 100 + os.getpid() % 100))


@pytest.fixture
def start_node(domain_id, tmp_path):
    """Factory: start_node(pkg, exe, name, params) -> NodeProcess; all stopped at teardown."""
    from tsr_koopman_ctrl.launcher import NodeProcess
    started = []

    def start(package, exe, name, params=None, extra_args=()):
        proc = NodeProcess(package, exe, name, params, domain_id=domain_id,
                           log_path=str(tmp_path / f'{name}.log'), extra_args=extra_args)
        started.append(proc)
        return proc

    yield start
    for proc in started:
        proc.stop()


class RosClient:
    """An rclpy node in the test process, on the test's domain."""

    def __init__(self, domain):
        import rclpy  # here, not at the top: the ROS-free tests must not need rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node('test_client', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate, timeout=10.0, what='condition'):
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise TimeoutError(f'timed out after {timeout} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.05)

    def spin_for(self, seconds):
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


@pytest.fixture
def ros(domain_id):
    client = RosClient(domain_id)
    yield client
    client.close()
