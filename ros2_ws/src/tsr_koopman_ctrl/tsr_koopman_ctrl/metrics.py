"""Deployment figures of merit, ROS-free: settle time into the 1% zone, swing, overshoot, tension.

The 1% zone (paper, Section IV-D): |theta| <= 0.01 and |l - 1| <= 0.01, reached and kept.
"""

import numpy as np

from tsr_sim.dynamics import LENGTH_OFFSET, THETA

ZONE = 0.01


def settle_index(states, zone=ZONE):
    """First index from which the state stays in the zone to the end; None if it never does."""
    inside = (np.abs(states[:, THETA]) <= zone) & (np.abs(states[:, LENGTH_OFFSET]) <= zone)
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    return 0 if outside.size == 0 else int(outside[-1]) + 1


def deployment_summary(tau, states, tensions):
    """Figures of one deployment; tau (N,), states (N, n), tensions (N-1,) or (N,)."""
    index = settle_index(states)
    dt = np.diff(tau)
    u = np.asarray(tensions)[:dt.size]
    return {
        'settle_tau': None if index is None else float(tau[index] - tau[0]),
        'theta_min': float(states[:, THETA].min()),
        'theta_max': float(states[:, THETA].max()),
        'length_overshoot': float(max(0.0, states[:, LENGTH_OFFSET].max())),
        'tension_max': float(u.max()) if u.size else 0.0,
        'tension_integral': float(np.sum(u * dt)),
        'final_state': states[-1].tolist(),
        'duration_tau': float(tau[-1] - tau[0]),
    }
