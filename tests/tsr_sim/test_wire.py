"""The wire module, ROS-free: names resolve like rclpy's, conversions round-trip."""

from types import SimpleNamespace

import numpy as np
import pytest

from tsr_sim import dynamics, wire
from tsr_sim.units import Scale


@pytest.mark.parametrize('name, namespace, resolved', [
    ('tsr/state', '/', '/tsr/state'), ('tsr/state', '/tsr1', '/tsr1/tsr/state'),
    ('tsr/state', '/a/b/', '/a/b/tsr/state'), ('/clock', '/tsr1', '/clock')])
def test_names_resolve_in_the_namespace(name, namespace, resolved):
    assert wire.resolve(name, namespace) == resolved


def test_loop_topics_are_relative_except_the_clock():
    for topic in wire.LOOP_TOPIC_TYPES:
        assert topic == wire.CLOCK_TOPIC or not topic.startswith('/')


def message(si, out_of_plane=False):
    """A duck-typed TsrState, as the bag reader decodes one."""
    beta = (si[4], si[5]) if out_of_plane else (0.0, 0.0)
    return SimpleNamespace(theta=si[0], theta_rate=si[1], length=si[2], length_rate=si[3],
                           has_out_of_plane=out_of_plane, beta=beta[0], beta_rate=beta[1])


def test_state_from_msg_reads_the_si_layout_of_units():
    x = np.array([0.1, -0.2, -0.5, 0.3, 0.05, -0.01])
    si = Scale().state_to_si(x)
    np.testing.assert_array_equal(wire.state_from_msg(message(si[:4])), si[:4])
    np.testing.assert_array_equal(wire.state_from_msg(message(si, True)), si)
    assert wire.state_from_msg(message(si, True), dynamics.PLANAR_DIM).size == 4
    np.testing.assert_allclose(Scale().state_from_si(wire.state_from_msg(message(si, True))), x)
