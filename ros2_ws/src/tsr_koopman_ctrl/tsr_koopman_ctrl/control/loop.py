"""A law closed on the dynamics module, ROS-free: what the DDS loop does, step for step."""

import numpy as np
from tsr_sim import dynamics

from tsr_koopman_ctrl.control.limiter import TensionLimiter


def closed_loop(controller, x0, steps, h=dynamics.PAPER_STEP, substeps=10,
                u_max=dynamics.TENSION_LIMIT):
    """Run `controller` on the dynamics module: returns states (k+1, n) and tensions (k,), k =
    steps unless the state would leave the domain: then the loop halts there, as the
    simulator does, and k < steps."""
    limiter = TensionLimiter(u_max)
    controller.reset()
    states = [np.asarray(x0, dtype=float)]
    tensions = []
    for _ in range(steps):
        u = limiter(controller.compute(states[-1]))
        nxt = dynamics.step(states[-1], u, h, substeps)
        if not dynamics.in_domain(nxt):
            break
        tensions.append(u)
        states.append(nxt)
    return np.array(states), np.array(tensions)
