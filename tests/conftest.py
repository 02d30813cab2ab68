"""Shared fixtures.

ROS-free: the shipped model's path, a small sampled data set and a tiny trained model.
ROS (tests marked `ros`): the fixtures users import into their own suites
(`tsr_koopman_ctrl.testing`: a DDS domain and a namespace of each test's own, nodes as separate
processes, a whole loop, an in-test rclpy node on the same domain). A test that uses them must
carry the `ros` marker, so that `pytest -m "not ros"` runs the core alone.
"""

import os
import pathlib

import pytest

#: Tiny models and small matrices: one thread each is faster than threads fighting over the
#: cores with the ROS processes (measured: the learning tests 141 s with torch's default of two
#: threads on a loaded 2-core machine, 18 s with one). Set before torch or numpy load.
os.environ.setdefault('OMP_NUM_THREADS', '1')

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED_MODEL = str(ROOT / 'models' / 'koopman_default')
ROS_FIXTURES = {'ros', 'start_node', 'ros_domain', 'ros_namespace', 'tsr_loop'}
pytest_plugins = ['tsr_koopman_ctrl.testing']


def pytest_collection_modifyitems(items):
    for item in items:
        if ROS_FIXTURES & set(item.fixturenames) and item.get_closest_marker('ros') is None:
            raise pytest.UsageError(f'{item.nodeid} uses ROS fixtures without the ros marker')


# ---------------------------------------------------------------------------------------------
# ROS-free

def tiny_config():
    from tsr_koopman_ctrl.model import model_file
    return model_file.KoopmanConfig.from_dict(dict(
        lift_dim=4, hidden=16, layers=2, input_hidden=8, input_layers=1, input_terms=3,
        epochs=4, batch_size=32, learning_rate=3e-3))


def step_differences(model, x, u, eps=1e-6):
    """(d x+ / d x (N, n, n), d x+ / d u (N, n)) of `model.step` by central differences: the
    reference its analytic `step_jacobians` are checked against."""
    import numpy as np
    by_state = np.stack([(model.step(x + eps * e, u) - model.step(x - eps * e, u)) / (2 * eps)
                         for e in np.eye(x.shape[1])], axis=2)
    by_tension = (model.step(x, u + eps) - model.step(x, u - eps)) / (2 * eps)
    return by_state, by_tension


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
# ROS: the fixtures users get (tsr_koopman_ctrl.testing): ros_domain, ros_namespace, ros,
# start_node, tsr_loop
