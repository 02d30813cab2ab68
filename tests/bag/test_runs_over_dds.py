"""Bags of real loops over DDS, every node on sim time: a reset makes two runs, two namespaced
loops on one domain one run each, the final state always reaches the bag, and recorders started
together write distinct bags."""

import os
import re
import signal
import time

import numpy as np
import pytest
from tsr_sim import dynamics
from tsr_sim.units import Scale

from tsr_koopman_ctrl.bag import BagReader, read_loop, read_runs
from tsr_koopman_ctrl.control import closed_loop, make_controller
from tsr_koopman_ctrl.learning import recorded

pytestmark = pytest.mark.ros

#: Where the reset sends the plant (dimensionless): another start than the paper's.
RESET_STATE = np.array([0.2, 0.0, -0.6, 0.3])
FINISHED = 2


def reset_request(state):
    from tsr_msgs.srv import ResetSim
    si = Scale().state_to_si(state)
    return ResetSim.Request(theta=si[0], theta_rate=si[1], length=si[2], length_rate=si[3])


def test_a_sim_time_bag_across_a_reset_reads_as_two_runs(tsr_loop, ros):
    """On sim time the reset sends every clock back to 0, and the headers with it, while the
    log times (receptions) go on in the order received, as stock tools play a bag; the runs
    come from the simulator's run number: run 0 up to the reset, run 1 from the reset state to
    the end, each command with its own run's state (run 1 is the ROS-free loop from
    the reset state, step for step). Lockstep runs ~1000 steps a second: run 0 is long and is
    cut by the reset; run 1 ends at `max_steps`, set (live) once it has begun."""
    from tsr_msgs.srv import ResetSim
    loop = tsr_loop(law='linear_lqr', steps=10 ** 6)
    namespace = loop.deployment.namespace
    loop.wait_for_step(60)
    response = ros.call(ResetSim, f'{namespace}/tsr/reset', reset_request(RESET_STATE))
    assert response.success, response.message
    # Run 1 finishes at step 1000, or where it is if it got there first.
    assert ros.set_parameters(f'{namespace}/tsr_sim', {'max_steps': 1000}) == [(True, '')]
    loop.deployment.wait()
    loop.deployment.stop()
    bag = loop.deployment.bag
    first, second = read_runs(bag)
    assert (first.sim_run, second.sim_run) == (0, 1)
    assert first.step.tolist() == list(range(first.step[-1] + 1)) and first.step[-1] >= 60
    steps = int(second.step[-1])
    assert steps >= 1000 and second.step.tolist() == list(range(steps + 1))
    np.testing.assert_allclose(second.x[0], RESET_STATE, atol=1e-12)
    want_x, want_u = closed_loop(make_controller('linear_lqr'), RESET_STATE, steps)
    np.testing.assert_allclose(second.x, want_x, atol=1e-9)
    np.testing.assert_allclose(second.u[:steps], want_u, atol=1e-9)
    assert second.sim_status.status == FINISHED and second.sim_status.step == steps
    assert not first.halted and first.sim_status.run == 0
    # Headers on sim time went back at the reset; log times never go back.
    states = [(m.log_time_ns, d.run, d.step, d.header.stamp.sec + d.header.stamp.nanosec * 1e-9)
              for m, d in BagReader(bag).decoded() if m.type == 'tsr_msgs/msg/TsrState']
    log_times = [state[0] for state in states]
    assert log_times == sorted(log_times)
    first_of_run_1 = next(stamp for _, run, step, stamp in states if (run, step) == (1, 1))
    assert first_of_run_1 < first.tau[-1] / Scale().orbit_rate
    assert all(log_time > 10 ** 18 for log_time in log_times)       # receptions, wall clock
    windows = recorded.read_windows(bag, steps=30)
    gaps = windows.provenance['gaps']
    assert gaps['resets'] == 1 and [r['states'] for r in gaps['loop_runs']] == [
        first.step.size, steps + 1]
    assert gaps['windows'] == first.step[-1] // 30 + steps // 30


def test_two_namespaced_sim_time_loops_on_one_domain_each_read_as_one_run(tsr_loop):
    """Two simulators on one domain, each loop's /clock remapped into its namespace (as a
    Deployment does): each bag holds its own loop's clock only, never going back, and is one
    run, every step from 0, the ROS-free loop's."""
    steps = 200
    loops = [tsr_loop(law='linear_lqr', steps=steps, namespace=ns) for ns in ('/A', '/B')]
    runs = [loop.finish() for loop in loops]
    assert runs[0].bag != runs[1].bag
    want_x, want_u = closed_loop(make_controller('linear_lqr'), dynamics.PAPER_INITIAL_STATE,
                                 steps)
    for run, namespace in zip(runs, ('/A', '/B')):
        (only,) = read_runs(run.bag)
        assert only.namespace == namespace
        assert only.step.tolist() == list(range(steps + 1))
        np.testing.assert_allclose(only.x, want_x, atol=1e-9)
        np.testing.assert_allclose(only.u[:steps], want_u, atol=1e-9)
        assert only.sim_status.status == FINISHED
        assert recorded.read_windows(run.bag, steps=30).provenance['gaps']['resets'] == 0
        clocks = [(m.topic, d.clock.sec + d.clock.nanosec * 1e-9)
                  for m, d in BagReader(run.bag).decoded() if m.type == 'rosgraph_msgs/msg/Clock']
        assert clocks and {topic for topic, _ in clocks} == {f'{namespace}/clock'}
        seconds = [second for _, second in clocks]
        assert seconds == sorted(seconds)


def test_the_final_state_reaches_the_bag_of_a_recorder_that_fell_behind(tsr_loop, ros):
    """The recorder is paused (SIGSTOP) from step 20 until the simulator has finished: what
    was sent meanwhile overflows its transport's queue and must be sent again. The simulator
    waits for its readers' acknowledgements before it exits (`SimNode.close`), so the bag holds
    every state, the final one included, and the FINISHED status. Measured without that wait:
    177 of 901 states, the last at step 176."""
    steps = 900
    loop = tsr_loop(law='linear_lqr', steps=steps)
    loop.wait_for_step(20)
    recorder = loop.deployment.processes[0]
    os.kill(recorder.process.pid, signal.SIGSTOP)
    try:
        ros.spin_until(lambda: loop.status.status == FINISHED, timeout=120,
                       what='the end of the run')
    finally:
        os.kill(recorder.process.pid, signal.SIGCONT)
    recorded_loop = loop.finish().loop
    assert recorded_loop.step.tolist() == list(range(steps + 1))
    assert recorded_loop.sim_status.status == FINISHED
    assert recorded_loop.sim_status.step == steps


def test_the_final_state_and_status_are_in_every_bag_of_a_few_deploys(tsr_loop):
    steps = 50
    for _ in range(3):
        run = tsr_loop(law='linear_lqr', steps=steps).finish()
        loop = read_loop(run.bag)
        assert loop.step[-1] == steps and loop.sim_status.status == FINISHED, run.bag


def test_recorders_started_together_write_distinct_bags(start_node, tmp_path):
    bags = tmp_path / 'bags'
    recorders = [start_node('tsr_koopman_ctrl', 'recorder_node', f'tsr_recorder_{k}',
                            {'output_dir': str(bags)}) for k in range(2)]
    deadline = time.monotonic() + 60.0
    while not (bags.is_dir() and len(os.listdir(bags)) >= 2) and time.monotonic() < deadline:
        assert all(recorder.running() for recorder in recorders)
        time.sleep(0.1)
    for recorder in recorders:
        assert recorder.stop() == 0
    names = sorted(os.listdir(bags))
    assert len(names) == 2, names
    for name in names:
        assert re.fullmatch(r'tsr_\d{8}_\d{6}_\d{6}_[0-9a-f]{6}', name)
