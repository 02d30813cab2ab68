"""Every node's /diagnostics says how its executor thread is scheduled, and warns when the
real-time priority it asked for (`thread_priority`) was refused."""

import os
import threading
import types

import pytest
from tsr_sim.ros_io import Health, scheduling, with_scheduling


class Node:
    """What `with_scheduling` asks of a node: its `thread_priority`, if it declared one."""

    def __init__(self, priority):
        self.priority = priority

    def has_parameter(self, name):
        return name == 'thread_priority' and self.priority is not None

    def get_parameter(self, name):
        return types.SimpleNamespace(value=self.priority)


def test_a_refused_priority_is_a_warning_on_a_normal_thread():
    assert scheduling() == 'normal'
    assert with_scheduling(Node(50), Health.OK, 'ok', {'a': 1}) == (
        Health.WARN, 'thread_priority 50 refused: running at normal priority',
        {'a': 1, 'scheduling': 'normal'})
    for asked in (0, None):
        assert with_scheduling(Node(asked), Health.OK, 'ok', {}) == (
            Health.OK, 'ok', {'scheduling': 'normal'})
    assert with_scheduling(Node(50), Health.ERROR, 'halted', {})[:2] == (Health.ERROR, 'halted')


def test_a_real_time_thread_reports_its_priority():
    seen = []

    def worker():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        except OSError:
            seen.append(None)
            return
        seen.append(with_scheduling(Node(10), Health.OK, 'ok', {}))
    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    if seen == [None]:
        pytest.skip('this host refuses real-time scheduling')
    assert seen == [(Health.OK, 'ok', {'scheduling': 'SCHED_FIFO 10'})]
