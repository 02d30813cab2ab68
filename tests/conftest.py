"""Shared fixtures.

ROS-free: the shipped model's path, a small sampled data set and a tiny trained model.
ROS (tests marked `ros`): an isolated DDS domain, nodes as separate processes (the installed
executables) and an in-test rclpy node on the same domain. A test that uses the ROS fixtures
must carry the `ros` marker, so that `pytest -m "not ros"` runs the core alone.
"""

import os
import pathlib
import time

import pytest

#: Tiny models and small matrices: one thread each is faster than threads fighting over the
#: cores with the ROS processes (measured: the learning tests 141 s with torch's default of two
#: threads on a loaded 2-core machine, 18 s with one). Set before torch or numpy load.
os.environ.setdefault('OMP_NUM_THREADS', '1')

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED_MODEL = str(ROOT / 'models' / 'koopman_default')
ROS_FIXTURES = {'ros', 'start_node', 'domain_id'}


def pytest_collection_modifyitems(items):
    for item in items:
        if ROS_FIXTURES & set(item.fixturenames) and item.get_closest_marker('ros') is None:
            raise pytest.UsageError(f'{item.nodeid} uses ROS fixtures without the ros marker')


# ---------------------------------------------------------------------------------------------
# ROS-free

def tiny_config():
    from tsr_koopman_ctrl.model import model_file
    return model_file.KoopmanConfig(lift_dim=4, hidden=16, layers=2, input_hidden=8,
                                    input_layers=1, input_terms=3, epochs=4, batch_size=32,
                                    learning_rate=3e-3)


@pytest.fixture(scope='session')
def small_data():
    from tsr_koopman_ctrl.learning import dataset as datasets
    return datasets.sample(datasets.SamplingConfig(trajectories=400, seed=3))[0]


@pytest.fixture(scope='session')
def tiny_model(small_data, tmp_path_factory):
    """(model directory, torch model, trainer) of a tiny model trained for 4 epochs."""
    from tsr_koopman_ctrl.learning.trainer import save_model, Trainer
    out = tmp_path_factory.mktemp('model')
    config = tiny_config()
    trainer = Trainer(config, out, progress=False)
    net = trainer.fit(small_data)
    save_model(out, net, config, trainer, small_data, small_data, 1.0, 'test')
    return out, net, trainer


# ---------------------------------------------------------------------------------------------
# ROS

@pytest.fixture(scope='session')
def domain_id():
    """A DDS domain of our own: ROS_DOMAIN_ID when the caller set one, else one of the
    launcher's free domains (1..101) derived from the process id, so parallel runs and other
    ROS graphs do not interfere."""
    from tsr_koopman_ctrl.tools.launcher import FREE_DOMAIN_IDS
    for name in ('ROS_DOMAIN_ID', 'TSR_TEST_DOMAIN'):
        if os.environ.get(name):
            return int(os.environ[name])
    return FREE_DOMAIN_IDS[os.getpid() % len(FREE_DOMAIN_IDS)]


@pytest.fixture
def start_node(domain_id, tmp_path):
    """Factory: start_node(pkg, exe, name, params, ...) -> NodeProcess; all stopped at
    teardown. Logs go to tmp_path/<name>.log."""
    from tsr_koopman_ctrl.tools.launcher import NodeProcess
    started = []

    def start(package, exe, name, params=None, extra_args=(), namespace=None, cwd=None):
        proc = NodeProcess(package, exe, name, params, domain_id=domain_id,
                           log_path=str(tmp_path / f'{name}.log'), extra_args=extra_args,
                           namespace=namespace, cwd=cwd)
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

    def spin_for(self, seconds, until=None):
        """Spin for `seconds`, or less if `until()` becomes true."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not (until and until()):
            self.executor.spin_once(timeout_sec=0.05)

    def call(self, service_type, name, request, timeout=10.0):
        """Call a service and wait for its response."""
        client = self.node.create_client(service_type, name)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                raise TimeoutError(f'no service {name} after {timeout} s')
            future = client.call_async(request)
            self.spin_until(future.done, timeout, what=f'the response of {name}')
            return future.result()
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
                             GetParameters.Request(names=list(names)), timeout)
        return {name: parameter_value_to_python(value)
                for name, value in zip(names, response.values)}

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


@pytest.fixture
def ros(domain_id):
    client = RosClient(domain_id)
    yield client
    client.close()
