"""The minimum-time deployment frontier a controller's settle time is divided by.

A controller that swings to max |theta| = s cannot deploy faster than the minimum-time solution
with |theta| <= s (docs/frontier.md). The table holds minimum deployment times from the paper's
start with 0 <= u <= 5 against the swing allowed; 1.05 rad is where the unconstrained optimum
swings. Below 0.4 rad only the u >= 0 figures exist (20.5 tau at 0.2, 11.7 at 0.3): lower bounds.
"""

import numpy as np

from tsr_koopman_ctrl.evaluation.starts import PAPER_START

FRONTIER_SWING_TAU = {PAPER_START: ((0.2, 20.5), (0.3, 11.7), (0.4, 8.8), (0.6, 4.3),
                                    (0.8, 3.3), (1.05, 2.7))}


def frontier_tau(start, swing):
    """Minimum deployment time (tau) from `start` at a swing max |theta| (interpolated in the
    table), or None where the start has no tabulated frontier."""
    table = FRONTIER_SWING_TAU.get(tuple(float(v) for v in start))
    if table is None:
        return None
    swings, taus = zip(*table)
    return float(np.interp(swing, swings, taus))
