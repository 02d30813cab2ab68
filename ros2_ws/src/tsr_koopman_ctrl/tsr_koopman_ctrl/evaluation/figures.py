"""The figures of a deployment, computed by one function every tool uses (`run_figures`).

The 1% zone (paper, Section IV-D): |theta| <= 0.01 and |l - 1| <= 0.01, reached and kept.
"""

import numpy as np
from tsr_sim.dynamics import LENGTH_OFFSET, PAPER_STEP, THETA

from tsr_koopman_ctrl.evaluation.frontier import frontier_tau

ZONE = 0.01
#: How far past a swing bound a run may swing and still have held it [rad]: the studies'
#: verdict (the NMPC's own margin is 0.003 rad).
SWING_TOLERANCE = 0.005


def in_zone(states, zone=ZONE):
    """Which states (..., n) lie in the zone: |theta| <= zone and |l - 1| <= zone."""
    states = np.asarray(states)
    return (np.abs(states[..., THETA]) <= zone) & (np.abs(states[..., LENGTH_OFFSET]) <= zone)


def settle_index(states, zone=ZONE):
    """First index from which the state stays in the zone to the end; None if it never does."""
    inside = in_zone(states, zone)
    if not inside[-1]:
        return None
    outside = np.flatnonzero(~inside)
    return 0 if outside.size == 0 else int(outside[-1]) + 1


def run_figures(tau, states, tensions, start=None, halted=False):
    """Figures of one deployment: tau (N,), states (N, n), tensions (N-1,) or (N,) (extra values
    ignored). `start` (the initial state) picks the frontier; `halted`: the state left the
    domain after the last recorded step.

    Keys: settle_tau (None if the zone was not reached and kept, or the run halted), swing
    (max |theta|), theta_min, theta_max, length_overshoot (max(0, max l - 1)), tension_max,
    tension_integral (sum u dtau), final_state, duration_tau, halted, frontier_tau and
    frontier_ratio (None without a settle time or a tabulated frontier).
    """
    tau, states = np.asarray(tau, dtype=float), np.asarray(states, dtype=float)
    if states.ndim != 2 or not len(states) or tau.shape != (len(states),):
        raise ValueError(f'run_figures takes tau (N,) and states (N, n) with N >= 1, got tau '
                         f'{tau.shape} and states {states.shape}')
    index = None if halted else settle_index(states)
    dt = np.diff(tau)
    u = np.asarray(tensions, dtype=float)[:dt.size]
    settle = None if index is None else float(tau[index] - tau[0])
    swing = float(np.abs(states[:, THETA]).max())
    frontier = frontier_tau(start, swing) if start is not None and settle is not None else None
    return {
        'settle_tau': settle,
        'swing': swing,
        'theta_min': float(states[:, THETA].min()),
        'theta_max': float(states[:, THETA].max()),
        'length_overshoot': float(max(0.0, states[:, LENGTH_OFFSET].max())),
        'tension_max': float(u.max()) if u.size else 0.0,
        'tension_integral': float(np.sum(u * dt)),
        'final_state': states[-1].tolist(),
        'duration_tau': float(tau[-1] - tau[0]),
        'halted': bool(halted),
        'frontier_tau': frontier,
        'frontier_ratio': None if frontier is None else settle / frontier,
    }


def closed_loop_figures(law, start, steps=2000, **loop):
    """`run_figures` of `law` closed on the dynamics module from `start` for `steps` steps (the
    DDS loop is step-identical to this one), with the law's solver fallbacks; `loop`: the
    options of `control.closed_loop` (e.g. `plant`, a plant unlike the model)."""
    from tsr_koopman_ctrl.control.loop import closed_loop
    states, tensions = closed_loop(law, start, steps, **loop)
    figures = run_figures(np.arange(len(states)) * PAPER_STEP, states, tensions, start=start,
                          halted=len(states) <= steps)
    figures['fallbacks'] = law.fallbacks
    return figures
