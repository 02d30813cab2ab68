"""The launcher: the DDS domain a run picks, the environment of the processes it starts."""

import os
import random

import pytest

from tsr_koopman_ctrl.launcher import FREE_DOMAIN_IDS, ONE_THREAD, random_domain_id

#: Linux's default ephemeral port range starts here (/proc/sys/net/ipv4/ip_local_port_range).
EPHEMERAL_START = 32768


def rtps_ports(domain, participants):
    """The UDP ports a DDS participant binds in `domain` (DDSI-RTPS 2.5, 9.6.1.1: port base
    7400, domain gain 250, participant gain 2, offsets 0 and 1 multicast, 10 and 11 unicast)."""
    base = 7400 + 250 * domain
    multicast = [base, base + 1]
    unicast = [base + offset + 2 * p for p in range(participants) for offset in (10, 11)]
    return multicast + unicast


def test_a_drawn_domain_keeps_every_port_below_the_ephemeral_range(monkeypatch):
    monkeypatch.delenv('ROS_DOMAIN_ID', raising=False)
    # 50 participants a host: a deployment has three, an integration test a handful more.
    worst = max(max(rtps_ports(d, 50)) for d in FREE_DOMAIN_IDS)
    assert worst < EPHEMERAL_START
    rng = random.Random(0)
    drawn = {random_domain_id(rng) for _ in range(2000)}
    assert drawn == set(FREE_DOMAIN_IDS)


def test_a_drawn_domain_is_never_the_callers_own(monkeypatch):
    for written in ('42', '042', ' 42 '):
        monkeypatch.setenv('ROS_DOMAIN_ID', written)
        rng = random.Random(1)
        drawn = {random_domain_id(rng) for _ in range(2000)}
        assert drawn == set(FREE_DOMAIN_IDS) - {42}
    monkeypatch.setenv('ROS_DOMAIN_ID', 'not a number')     # rcl would refuse it; 0 is out
    rng = random.Random(2)
    assert {random_domain_id(rng) for _ in range(2000)} == set(FREE_DOMAIN_IDS)


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
