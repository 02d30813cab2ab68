"""The closed loop near the target, linearised: how fast and how well damped a law settles.

A law's settle time into the 1% zone is set, from starts near the target, by its slowest and
least damped closed-loop modes. Those are the eigenvalues of the plant's one-step map closed
with the law's gain at the target (both linearised by central differences), a figure GNC
engineers read before any simulation: e.g. the cross-tuned Koopman-LQR's least damped pair is
at zeta 0.22, which the tuning starts (all at theta = 0) barely excite (docs/comparison.md).
"""

import numpy as np
from tsr_sim import dynamics

#: Central-difference step on the state and the tension.
STEP = 1e-5


def local_closed_loop(law, h=dynamics.PAPER_STEP):
    """{'gain': du/dx at the target (4,), 'poles': closed-loop poles in 1/tau (continuous
    equivalents log(z) / h, sorted by decay rate), 'damping': their damping ratios,
    'slowest_decay': the smallest decay rate [1/tau]} of `law` on the planar plant at x = 0.

    The law is reset before each call, so a law with a state of its own (the fractional PD's
    memory, the offset-free wrapper's estimate) is linearised without it: use the bare law.
    """
    target = dynamics.equilibrium_state()
    tension = dynamics.EQUILIBRIUM_TENSION
    gain = np.zeros(dynamics.PLANAR_DIM)
    step_a = np.zeros((dynamics.PLANAR_DIM, dynamics.PLANAR_DIM))
    for i in range(dynamics.PLANAR_DIM):
        offset = np.zeros(dynamics.PLANAR_DIM)
        offset[i] = STEP
        gain[i] = (tension_at(law, target + offset)
                   - tension_at(law, target - offset)) / (2 * STEP)
        step_a[:, i] = (dynamics.planar_step(target + offset, tension, h)
                        - dynamics.planar_step(target - offset, tension, h)) / (2 * STEP)
    step_b = (dynamics.planar_step(target, tension + STEP, h)
              - dynamics.planar_step(target, tension - STEP, h)) / (2 * STEP)
    poles = np.log(np.linalg.eigvals(step_a + np.outer(step_b, gain)).astype(complex)) / h
    poles = poles[np.argsort(-poles.real)]
    damping = -poles.real / np.abs(poles)
    return {'gain': gain, 'poles': poles, 'damping': damping,
            'slowest_decay': float(-poles.real.max())}


def tension_at(law, x):
    law.reset()
    return float(law.compute(np.asarray(x, dtype=float)))
