"""The main job over DDS: simulator, controller and recorder as three processes."""

import pathlib

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

from tsr_koopman_ctrl import controllers, deploy
from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl.metrics import settle_index
from tsr_sim import dynamics
from tsr_sim.units import Scale

SHIPPED_MODEL = str(pathlib.Path(__file__).resolve().parents[1] / 'models' / 'koopman_default')


def test_deployment_over_dds_matches_the_ros_free_loop_and_leaves_a_bag(tmp_path, domain_id):
    steps = 400
    args = ['--controller', 'linear_lqr', '--steps', str(steps), '--out', str(tmp_path / 'out'),
            '--bags', str(tmp_path / 'bags'), '--domain', str(domain_id)]
    assert deploy.main(args) == 0

    (bag_path,) = (tmp_path / 'bags').iterdir()
    loop = read_loop(str(bag_path), Scale())
    assert not loop['report'].recovered
    assert loop['step'].tolist() == list(range(steps + 1))
    # Lockstep makes the DDS loop step-identical to the ROS-free one.
    want_x, want_u = controllers.closed_loop(controllers.LinearisedLqr(),
                                             dynamics.PAPER_INITIAL_STATE, steps)
    np.testing.assert_allclose(loop['x'], want_x, atol=1e-9)
    np.testing.assert_allclose(loop['u'][:steps], want_u, atol=1e-9)

    with AnyReader([bag_path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        first = next(reader.deserialize(raw, c.msgtype)
                     for c, _, raw in reader.messages() if c.topic == '/tsr/state')
    assert counts['/tsr/state'] == steps + 1 and counts['/tsr/tension_cmd'] >= steps
    assert counts['/clock'] >= steps
    assert abs(first.length - 1000.0) < 1e-9   # SI on the wire: l = 0.01 of 100 km
    (run_dir,) = (tmp_path / 'out').iterdir()
    assert (run_dir / 'deployment.png').stat().st_size > 10_000
    assert 'linear_lqr' in (run_dir / 'summary.md').read_text()


def test_shipped_model_deploys_into_the_zone_over_dds_like_the_ros_free_loop(tmp_path, domain_id):
    """The main job as the README runs it (2000 steps, koopman_mpc, the shipped model)."""
    steps = 2000
    args = ['--controller', 'koopman_mpc', '--model', SHIPPED_MODEL, '--steps', str(steps),
            '--out', str(tmp_path / 'o'), '--bags', str(tmp_path / 'b'),
            '--domain', str(domain_id)]
    assert deploy.main(args) == 0
    (bag_path,) = (tmp_path / 'b').iterdir()
    loop = read_loop(str(bag_path), Scale())
    mpc = controllers.KoopmanMpc(SHIPPED_MODEL)
    want_x, want_u = controllers.closed_loop(mpc, dynamics.PAPER_INITIAL_STATE, steps)
    np.testing.assert_allclose(loop['x'], want_x, atol=1e-7)
    np.testing.assert_allclose(loop['u'][:steps], want_u, atol=1e-7)
    assert settle_index(loop['x']) is not None
    (run_dir,) = (tmp_path / 'o').iterdir()
    summary = (run_dir / 'summary.md').read_text()
    assert 'koopman_mpc' in summary and ' / ' in summary   # compute times parsed from the log
