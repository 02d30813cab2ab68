"""The launcher: the DDS domain a run picks (free on the host, reserved), the environment and
the end of the processes it starts."""

import os
import random
import socket
import subprocess
import sys

import pytest

from tsr_koopman_ctrl import launcher
from tsr_koopman_ctrl.launcher import (domain_in_use, domain_ports, FREE_DOMAIN_IDS, ONE_THREAD,
                                       reserve_domain)

#: Linux's default ephemeral port range starts here (/proc/sys/net/ipv4/ip_local_port_range).
EPHEMERAL_START = 32768


def rtps_ports(domain, participants):
    """The UDP ports a DDS participant binds in `domain` (DDSI-RTPS 2.5, 9.6.1.1: port base
    7400, domain gain 250, participant gain 2, offsets 0 and 1 multicast, 10 and 11 unicast)."""
    base = 7400 + 250 * domain
    multicast = [base, base + 1]
    unicast = [base + offset + 2 * p for p in range(participants) for offset in (10, 11)]
    return multicast + unicast


@pytest.fixture
def quiet_host(monkeypatch, tmp_path):
    """No DDS port bound, no caller's domain, lock files of the test's own: the draw alone."""
    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)
    monkeypatch.setattr(launcher, 'bound_udp_ports', lambda: set())
    return str(tmp_path / 'locks')


def draws(lock_dir, rng, count=2000, **options):
    drawn = set()
    for _ in range(count):
        with reserve_domain(rng, lock_dir=lock_dir, **options) as reservation:
            drawn.add(reservation.id)
    return drawn


def test_a_drawn_domain_keeps_every_port_below_the_ephemeral_range(quiet_host):
    # 50 participants a host: a deployment has three, an integration test a handful more.
    worst = max(max(rtps_ports(d, 50)) for d in FREE_DOMAIN_IDS)
    assert worst < EPHEMERAL_START
    assert all(set(rtps_ports(d, 50)) <= set(domain_ports(d)) for d in FREE_DOMAIN_IDS)
    assert draws(quiet_host, random.Random(0)) == set(FREE_DOMAIN_IDS)


def test_a_drawn_domain_is_never_the_callers_own(quiet_host, monkeypatch):
    for written in ('42', '042', ' 42 '):
        monkeypatch.setenv('ROS_DOMAIN_ID', written)
        assert draws(quiet_host, random.Random(1)) == set(FREE_DOMAIN_IDS) - {42}
    monkeypatch.setenv('ROS_DOMAIN_ID', 'not a number')     # rcl would refuse it; 0 is out
    assert draws(quiet_host, random.Random(2)) == set(FREE_DOMAIN_IDS)


def test_domains_held_at_once_never_collide_and_a_released_one_is_drawn_again(quiet_host):
    """Every draw with the same seed tries the same order: only the locks keep them apart."""
    held = [reserve_domain(random.Random(3), lock_dir=quiet_host) for _ in FREE_DOMAIN_IDS]
    assert sorted(r.id for r in held) == list(FREE_DOMAIN_IDS)
    with pytest.raises(RuntimeError, match='no free DDS domain'):
        reserve_domain(random.Random(3), lock_dir=quiet_host)
    held[40].release()
    again = reserve_domain(random.Random(3), lock_dir=quiet_host)
    assert again.id == held[40].id
    for reservation in (*held, again):
        reservation.release()


def test_a_domain_another_process_holds_is_skipped_until_it_ends(quiet_host):
    holder = subprocess.Popen(
        [sys.executable, '-c', 'import sys\nfrom tsr_koopman_ctrl.launcher import '
         'reserve_domain\nr = reserve_domain(candidates=[7], lock_dir=sys.argv[1])\n'
         'print(r.id, flush=True)\nsys.stdin.read()', quiet_host],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == '7'
        assert draws(quiet_host, random.Random(4), 200, candidates=[7, 8]) == {8}
    finally:
        holder.kill()
        holder.wait()
    assert draws(quiet_host, random.Random(4), 200, candidates=[7]) == {7}


def test_a_domain_whose_dds_port_is_bound_is_in_use_and_skipped(monkeypatch, tmp_path):
    """A DDS participant of any program binds its domain's discovery port (SO_REUSEADDR,
    shared by the participants of the domain); the lock does not see it, the ports do."""
    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)
    locks = str(tmp_path / 'locks')
    free = [d for d in (90, 91, 92, 93) if not domain_in_use(d)][:2]
    assert len(free) == 2, 'the test needs two free domains of 90..93'
    taken, other = free
    participant = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    participant.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    participant.bind(('', domain_ports(taken)[0] + 12))     # a unicast port of participant 1
    try:
        assert domain_in_use(taken) and not domain_in_use(other)
        assert draws(locks, random.Random(5), 50, candidates=free) == {other}
        monkeypatch.setattr(launcher, 'bound_udp_ports', lambda: None)     # no /proc/net
        assert not domain_in_use(taken)      # the probe sees the discovery port only
        participant.close()
        participant = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        participant.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        participant.bind(('', domain_ports(taken)[0]))
        assert domain_in_use(taken) and not domain_in_use(other)
    finally:
        participant.close()


@pytest.mark.ros
def test_a_ros_participant_puts_its_domain_in_use_and_a_deployment_reserves_its_own(
        ros, ros_domain, tmp_path):
    from tsr_koopman_ctrl.deployment import Deployment
    assert domain_in_use(ros_domain)        # the test's own client is on it
    deployment = Deployment('linear_lqr', bags=str(tmp_path / 'bags'))
    assert deployment.domain != ros_domain
    with pytest.raises(RuntimeError):        # held: no other draw gets it
        reserve_domain(candidates=[deployment.domain])
    deployment.stop()
    reserve_domain(candidates=[deployment.domain]).release()


def test_a_started_process_runs_one_blas_thread_unless_the_caller_chose(monkeypatch):
    import json
    import subprocess
    import sys
    pytest.importorskip('threadpoolctl')
    from tsr_koopman_ctrl.launcher import child_environment
    probe = ('import json, numpy\nfrom threadpoolctl import threadpool_info\n'
             'print(json.dumps([p["num_threads"] for p in threadpool_info()'
             ' if p["user_api"] == "blas"]))')

    def blas_threads(environment):
        out = subprocess.run([sys.executable, '-c', probe], env=environment, check=True,
                             capture_output=True, text=True).stdout
        return json.loads(out)

    for name in ONE_THREAD:
        monkeypatch.delenv(name, raising=False)
    assert blas_threads(child_environment()) == [1]
    if os.cpu_count() >= 2:     # numpy's own default: a thread per core
        assert blas_threads(dict(os.environ))[0] > 1
    assert child_environment({'X_EXTRA': 'y'})['X_EXTRA'] == 'y'
    monkeypatch.setenv('OPENBLAS_NUM_THREADS', '2')     # the caller's choice stands
    assert child_environment()['OPENBLAS_NUM_THREADS'] == '2'
    assert 'OMP_NUM_THREADS' not in child_environment()
    if os.cpu_count() >= 2:
        assert blas_threads(child_environment()) == [2]


def test_one_thread_children_leaves_the_callers_environment_as_it_was(monkeypatch):
    from tsr_koopman_ctrl.launcher import one_thread_children
    for name in ONE_THREAD:
        monkeypatch.delenv(name, raising=False)
    before = dict(os.environ)
    with one_thread_children():
        assert os.environ['OPENBLAS_NUM_THREADS'] == '1' and os.environ['OMP_NUM_THREADS'] == '1'
    assert dict(os.environ) == before
    monkeypatch.setenv('OMP_NUM_THREADS', '3')     # the caller's choice: nothing added
    before = dict(os.environ)
    with one_thread_children():
        assert dict(os.environ) == before
    assert dict(os.environ) == before


def test_random_domain_id_keeps_its_domain_reserved(quiet_host, monkeypatch):
    monkeypatch.setattr(launcher, 'DOMAIN_LOCKS', quiet_host)
    domain = launcher.random_domain_id(random.Random(6))
    with pytest.raises(RuntimeError):
        reserve_domain(candidates=[domain], lock_dir=quiet_host)
    launcher._KEPT.pop().release()


@pytest.mark.ros
def test_a_node_process_never_outlives_the_python_process_that_started_it(ros_domain, tmp_path):
    """A program that starts a node and ends without stopping it (an exception, a test's
    timeout): the node is killed at the interpreter's exit."""
    program = ('import sys\nfrom tsr_koopman_ctrl.launcher import NodeProcess\n'
               "node = NodeProcess('tsr_sim', 'sim_node', 'tsr_sim', None,"
               " domain_id=int(sys.argv[1]), namespace='/t_survivor', log_path=sys.argv[2])\n"
               'print(node.process.pid, flush=True)\n'
               "raise SystemExit('left without stopping it')")
    done = subprocess.run([sys.executable, '-c', program, str(ros_domain),
                           str(tmp_path / 'sim.log')],
                          capture_output=True, text=True, timeout=60)
    pid = int(done.stdout.split()[0])
    assert done.returncode == 1
    with pytest.raises(ProcessLookupError):     # killed and reaped: no such process
        os.kill(pid, 0)
