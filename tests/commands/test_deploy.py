"""The main job over DDS: simulator, controller and recorder as three processes."""

import json

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
from tsr_sim import dynamics

from tsr_koopman_ctrl.bag import read_loop
from tsr_koopman_ctrl.control import closed_loop, LinearisedLqr, make_controller
from tsr_koopman_ctrl.evaluation import settle_index
from tsr_koopman_ctrl.commands import deploy
from tsr_koopman_ctrl.deployment import DeploymentError, watch

pytestmark = pytest.mark.ros


def deploy_args(tmp_path, ros_domain, namespace, *extra):
    """deploy's arguments on the test's domain, in `namespace` (None: deploy's default, the
    root namespace)."""
    return ['--out', str(tmp_path / 'out'), '--bags', str(tmp_path / 'bags'),
            '--domain', str(ros_domain), *(['--namespace', namespace] if namespace else []),
            *extra]


def test_deployment_over_dds_matches_the_ros_free_loop_and_leaves_a_bag(tmp_path, ros_domain):
    """In the root namespace on purpose: deploy's default, the bag's topics as the README
    shows them (the test's own domain keeps it apart from every other test)."""
    steps = 400
    assert deploy.main(deploy_args(tmp_path, ros_domain, None, '--law', 'linear_lqr',
                                   '--steps', str(steps))) == 0
    (bag_path,) = (tmp_path / 'bags').iterdir()
    loop = read_loop(str(bag_path))
    assert not loop.report.recovered
    assert loop.step.tolist() == list(range(steps + 1))
    # Lockstep makes the DDS loop step-identical to the ROS-free one.
    want_x, want_u = closed_loop(make_controller('linear_lqr'), dynamics.PAPER_INITIAL_STATE,
                                 steps)
    np.testing.assert_allclose(loop.x, want_x, atol=1e-9)
    np.testing.assert_allclose(loop.u[:steps], want_u, atol=1e-9)
    # The controller's status of every answered state is in the bag, with its compute time.
    assert loop.compute_time.size >= steps and np.all(loop.compute_time > 0.0)
    assert loop.controller_status.controller == 'linear_lqr'
    assert loop.sim_status.status == 2 and loop.sim_status.step == steps   # FINISHED

    with AnyReader([bag_path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        first = next(reader.deserialize(raw, c.msgtype)
                     for c, _, raw in reader.messages() if c.topic == '/tsr/state')
    assert counts['/tsr/state'] >= steps + 1 and counts['/tsr/tension_cmd'] >= steps
    assert counts['/clock'] >= steps and counts['/tsr/controller_status'] >= steps
    assert abs(first.length - 1000.0) < 1e-9   # SI on the wire: l = 0.01 of 100 km
    (run_dir,) = (tmp_path / 'out').iterdir()
    assert (run_dir / 'deployment.png').stat().st_size > 10_000
    (row,) = json.loads((run_dir / 'summary.json').read_text())
    assert row['compute_median_us'] == pytest.approx(np.median(loop.compute_time) * 1e6)
    assert_one_time_base(bag_path, steps)


def assert_one_time_base(bag_path, steps):
    """Every node ran on the simulator's clock: header stamps are sim time (t = tau / Omega
    from 0), and a command or status carries its state's stamp; the log times are the
    receptions, in the order recorded (what stock players play by)."""
    from tsr_sim.units import Scale
    from tsr_koopman_ctrl.bag import BagReader
    step_ns = Scale().tau_to_seconds(dynamics.PAPER_STEP) * 1e9
    end_ns = (steps + 1) * step_ns
    stamped, log_times = {}, []
    for message, decoded in BagReader(str(bag_path)).decoded():
        log_times.append(message.log_time_ns)
        stamp = getattr(decoded, 'header', None)
        if stamp is None:
            continue
        ns = stamp.stamp.sec * 10 ** 9 + stamp.stamp.nanosec
        assert 0 <= ns <= end_ns, message.topic
        step = getattr(decoded, 'step', None)
        if step is not None and step < 2 ** 63 and message.topic.startswith('/tsr/'):
            stamped.setdefault(message.topic.split('/')[-1], {})[step] = ns
    assert log_times == sorted(log_times) and log_times[0] > end_ns    # wall clock, in order
    states = stamped['state']
    assert states[steps] == pytest.approx(steps * step_ns, abs=1.0)
    for topic in ('tension_cmd', 'controller_status'):
        assert all(states[step] == ns for step, ns in stamped[topic].items()), topic


def test_shipped_model_deploys_into_the_zone_over_dds_like_the_ros_free_loop(
        tmp_path, ros_domain, ros_namespace):
    """The main job as the README runs it (2000 steps, koopman_nmpc, the shipped model)."""
    steps = 2000
    assert deploy.main(deploy_args(tmp_path, ros_domain, ros_namespace,
                                   '--steps', str(steps))) == 0
    (bag_path,) = (tmp_path / 'bags').iterdir()
    loop = read_loop(str(bag_path))
    assert loop.namespace == ros_namespace
    law = make_controller('koopman_nmpc')
    want_x, want_u = closed_loop(law, dynamics.PAPER_INITIAL_STATE, steps)
    np.testing.assert_allclose(loop.x, want_x, atol=1e-7)
    np.testing.assert_allclose(loop.u[:steps], want_u, atol=1e-7)
    assert settle_index(loop.x) is not None
    # One failed QP from this start, recovered by a cold start, in both loops.
    assert loop.controller_status.solver_fallbacks == law.fallbacks <= 1
    # The safety filter's verdicts travel in the bag: each step's, as the ROS-free loop's.
    assert loop.corrections == law.corrections
    assert loop.controller_status.safety_corrections == law.corrections
    certified = loop.certificate[:steps] == 'certified'
    assert certified.sum() == law.counts['certified'] > 0
    np.testing.assert_allclose(loop.requested[:steps][certified], loop.u[:steps][certified],
                               atol=1e-7)
    (run_dir,) = (tmp_path / 'out').iterdir()
    (row,) = json.loads((run_dir / 'summary.json').read_text())
    assert row['controller'] == 'koopman_nmpc' and row['settle_tau'] < 4.0
    assert row['safety_corrections'] == law.corrections
    assert row['frontier_ratio'] == pytest.approx(row['settle_tau'] / row['frontier_tau'])


def test_loop_under_a_namespace_reads_back_from_the_bag(tmp_path, ros_domain):
    steps = 100
    assert deploy.main(deploy_args(tmp_path, ros_domain, '/tsr1', '--law', 'linear_lqr',
                                   '--steps', str(steps))) == 0
    (bag_path,) = (tmp_path / 'bags').iterdir()
    loop = read_loop(str(bag_path))
    assert loop.namespace == '/tsr1'
    assert loop.step.tolist() == list(range(steps + 1))
    assert read_loop(str(bag_path), namespace='/tsr1').step.size == steps + 1
    with pytest.raises(ValueError, match='bag has no /other/tsr/state'):
        read_loop(str(bag_path), namespace='/other')
    with AnyReader([bag_path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        topics = {c.topic for c in reader.connections}
    # The loop's clock is in its namespace too (`Deployment.clock_remap`).
    assert {'/tsr1/tsr/state', '/tsr1/tsr/tension_cmd', '/tsr1/tsr/controller_status',
            '/tsr1/clock'} <= topics and '/clock' not in topics


def test_a_start_outside_the_domain_is_one_clear_line(tmp_path, ros_domain, ros_namespace,
                                                      capsys):
    with pytest.raises(SystemExit) as exit_info:
        deploy.main(deploy_args(tmp_path, ros_domain, ros_namespace,
                                '--x0', '0', '0', '-1.5', '0.5'))
    assert exit_info.value.code == 2
    assert 'outside the model domain' in capsys.readouterr().err


def test_a_node_failing_at_start_is_reported_with_its_log(tmp_path, ros_domain, ros_namespace,
                                                          capfd, monkeypatch):
    # deploy checks a plant file before any node starts (tools/test_cli.py); with that check
    # off, as for anything it could miss, the simulator refuses the value itself.
    from tsr_sim import plant as plant_module
    monkeypatch.setattr(plant_module, 'check_plant_parameter_values', lambda *args: None)
    plant = tmp_path / 'plant.yaml'
    plant.write_text('/**:\n  ros__parameters:\n    substeps: 0\n')
    assert deploy.main(deploy_args(tmp_path, ros_domain, ros_namespace, '--plant', str(plant),
                                   '--steps', '50')) == 1
    out, err = capfd.readouterr()
    assert 'tsr_sim exited with 2' in err
    assert 'cannot start:' in out and 'Parameter substeps out of range' in out


def test_a_node_failing_beside_the_simulator_is_reported_with_its_log_tail(
        tmp_path, ros_domain, ros_namespace):
    """deploy's watch, on real processes: a recorder that cannot start (deploy itself checks
    what it passes, so this is the path of an unexpected failure) stops the wait with the last
    lines of its log, while the simulator still waits for its subscribers."""
    from tsr_koopman_ctrl.launcher import NodeProcess
    sim = NodeProcess('tsr_sim', 'sim_node', 'tsr_sim', {'wait_for_subscribers': 2},
                      domain_id=ros_domain, log_path=str(tmp_path / 'sim.log'),
                      namespace=ros_namespace)
    recorder = None
    try:
        recorder = NodeProcess('tsr_koopman_ctrl', 'recorder_node', 'tsr_recorder',
                               {'output_dir': str(tmp_path), 'topics': ['state'],
                                'types': ['tsr_msgs/msg/NoSuchType']}, domain_id=ros_domain,
                               log_path=str(tmp_path / 'recorder.log'), namespace=ros_namespace)
        with pytest.raises(DeploymentError) as failed:
            watch(sim, (recorder,), timeout=60.0)
    finally:
        sim.stop()
        if recorder is not None:
            recorder.stop()
    report = str(failed.value)
    assert report.startswith('tsr_recorder exited early\n--- tsr_recorder exited with 2; '
                             f'last lines of {tmp_path}/recorder.log:\ncannot start: ')
    assert 'NoSuchType' in report


def test_excitation_and_run_info_are_recorded(tmp_path, ros_domain, ros_namespace):
    """The bag says what ran (both nodes' RunInfo) and what the controller added, and the
    commands are the law's plus exactly that excitation."""
    from tsr_koopman_ctrl.control.excitation import Excitation
    steps = 200
    assert deploy.main(deploy_args(tmp_path, ros_domain, ros_namespace, '--law', 'linear_lqr',
                                   '--steps', str(steps), '--set', 'excitation.kind=prbs',
                                   '--set', 'observer.disturbance=none',
                                   '--set', 'excitation.amplitude=0.5',
                                   '--set', 'excitation.seed=3')) == 0
    (bag_path,) = (tmp_path / 'bags').iterdir()
    loop = read_loop(str(bag_path))
    assert loop.run_info['controller']['excitation']['kind'] == 'prbs'
    assert loop.run_info['controller']['controller'] == 'linear_lqr'
    assert loop.run_info['simulator']['scale']['mass'] == 20.0
    expected = Excitation(kind='prbs', amplitude=0.5, seed=3)
    np.testing.assert_allclose(loop.excitation[:steps], [expected.next() for _ in range(steps)],
                               atol=1e-12)
    law = LinearisedLqr()
    want = np.clip([law.compute(x) for x in loop.x[:steps]] + loop.excitation[:steps], 0, 5)
    np.testing.assert_allclose(loop.u[:steps], want, atol=1e-9)
    # ... and the ROS-free loop with the same excitation is the same run.
    want_x, want_u = closed_loop(LinearisedLqr(), dynamics.PAPER_INITIAL_STATE, steps,
                                 excitation=Excitation(kind='prbs', amplitude=0.5, seed=3))
    np.testing.assert_allclose(loop.x, want_x, atol=1e-9)
    np.testing.assert_allclose(loop.u[:steps], want_u, atol=1e-9)


def test_a_plant_variant_over_dds_is_the_ros_free_one(tmp_path, ros_domain, ros_namespace):
    """--plant actuator_weak: the simulator runs the variant (its RunInfo says so) and the DDS
    loop equals the ROS-free loop on the same plant file, step for step."""
    from tsr_sim.plant import plant_parameters
    steps = 300
    assert deploy.main(deploy_args(tmp_path, ros_domain, ros_namespace, '--law', 'linear_lqr',
                                   '--steps', str(steps), '--plant', 'actuator_weak')) == 0
    (bag_path,) = (tmp_path / 'bags').iterdir()
    loop = read_loop(str(bag_path))
    assert loop.run_info['simulator']['plant'] == 'actuator_weak'
    assert loop.run_info['simulator']['variant']['actuator_gain'] == 0.9
    want_x, want_u = closed_loop(make_controller('linear_lqr'), dynamics.PAPER_INITIAL_STATE,
                                 steps, plant=plant_parameters('actuator_weak'))
    np.testing.assert_allclose(loop.x, want_x, atol=1e-9)
    np.testing.assert_allclose(loop.u[:steps], want_u, atol=1e-9)
    nominal_x, _ = closed_loop(make_controller('linear_lqr'), dynamics.PAPER_INITIAL_STATE,
                               steps)
    assert np.abs(nominal_x - want_x).max() > 1e-3     # the variant does change the run


def recorded_states(bags):
    """States a running recorder has flushed so far, from its bag's metadata.yaml (rewritten
    at every flush)."""
    import yaml
    for metadata in bags.glob('*/metadata.yaml'):
        try:
            info = yaml.safe_load(metadata.read_text())['rosbag2_bagfile_information']
        except (OSError, TypeError, KeyError, yaml.YAMLError):
            return 0
        return sum(t['message_count'] for t in info['topics_with_message_count']
                   if t['topic_metadata']['name'].endswith('/tsr/state'))
    return 0


def test_ctrl_c_closes_the_bag_summarises_the_steps_run_and_exits_130(tmp_path, ros_domain,
                                                                      ros_namespace):
    """Ctrl-C used to end `deploy` with status 0, and `loop` went on with the cut-short bag."""
    import contextlib
    import os
    import signal
    import subprocess
    import sys
    import time
    command = [sys.executable, '-m', 'tsr_koopman_ctrl.commands.deploy', '--law',
               'linear_lqr', '--steps', '100000',
               *deploy_args(tmp_path, ros_domain, ros_namespace)]
    # SIGINT as a terminal delivers it: a test run started in the background (`.ci/run &`)
    # inherits SIGINT ignored, which Python then leaves ignored.
    # Output to files: a pipe nobody reads while the loop runs could fill and stall it. A
    # session of its own: whatever happens, the group (deploy and its nodes) is killed after.
    with open(tmp_path / 'deploy.out', 'w') as out_file, \
            open(tmp_path / 'deploy.err', 'w') as err_file:
        proc = subprocess.Popen(
            command, stdout=out_file, stderr=err_file, start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120.0
        while (recorded_states(tmp_path / 'bags') < 100 and proc.poll() is None
               and time.monotonic() < deadline):      # some steps into the bag, under load
            time.sleep(0.2)
        reached = recorded_states(tmp_path / 'bags') >= 100
        running = proc.poll() is None
        if running:
            os.kill(proc.pid, signal.SIGINT)
            proc.wait(timeout=180)      # the nodes stop in turn, the bag is read
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    out, err = (tmp_path / 'deploy.out').read_text(), (tmp_path / 'deploy.err').read_text()
    assert running and reached, f'no 100 steps in the bag of a running deploy:\n{out}\n{err}'
    assert proc.returncode == 130, (out, err)
    assert '[deploy] interrupted: closing the bag' in out
    assert 'holds the steps run so far' in err and 'Traceback' not in err
    (bag_path,) = (tmp_path / 'bags').iterdir()
    loop = read_loop(str(bag_path))
    assert 0 < loop.step[-1] < 100000 and loop.step.tolist() == list(range(loop.step[-1] + 1))
    (run_dir,) = (tmp_path / 'out').iterdir()
    summary = json.loads((run_dir / 'summary.json').read_text())
    assert summary[0]['steps'] == int(loop.step[-1])


def test_deploy_bags_hold_every_step_from_0_under_load(tmp_path, ros_domain, ros_namespace):
    """Two processes keep both cores busy while three deployments run: each bag holds every
    state from step 0, its command and its controller status (the simulator starts once the
    controller and the recorder read, at the DDS level, what it and the controller publish)."""
    import subprocess
    import sys
    busy = [subprocess.Popen([sys.executable, '-c', 'while True: pass']) for _ in range(2)]
    try:
        steps = 200
        for run in range(3):
            out = tmp_path / f'run{run}'
            assert deploy.main(['--out', str(out / 'out'), '--bags', str(out / 'bags'),
                                '--domain', str(ros_domain), '--namespace', ros_namespace,
                                '--law', 'linear_lqr', '--steps', str(steps)]) == 0
            (bag_path,) = (out / 'bags').iterdir()
            loop = read_loop(str(bag_path))
            assert loop.step.tolist() == list(range(steps + 1)), run
            assert np.isfinite(loop.u[:steps]).all(), run
            statuses = {m.step for _, m in _decoded(bag_path, 'tsr_msgs/msg/ControllerStatus')}
            assert set(range(steps)) <= statuses, run
    finally:
        for process in busy:
            process.kill()
            process.wait()


def _decoded(bag_path, type_name):
    from tsr_koopman_ctrl.bag import BagReader
    return [(m, d) for m, d in BagReader(str(bag_path)).decoded() if m.type == type_name]
