"""A law closed on the simulated plant, ROS-free: what the DDS loop does, step for step.

The plant is the simulator's own (`tsr_sim.plant.Plant`, with its command checks, variants and
sensor noise), and the state and the command pass through SI units as on the wire, so a law
deployed here and over DDS in lockstep sees the same numbers.
"""

from collections.abc import Mapping
import numbers

import numpy as np
from tsr_sim import dynamics
from tsr_sim.plant import config_from_parameters, Plant, plant_parameters, Status
from tsr_sim.units import Scale

from tsr_koopman_ctrl.control.limiter import TensionLimiter
from tsr_koopman_ctrl.control.step import ControlStep, Outcome


def closed_loop(controller, x0, steps, h=dynamics.PAPER_STEP, substeps=10,
                u_max=dynamics.TENSION_LIMIT, plant=None, scale=None, excitation=None,
                compute_seconds=None):
    """Run `controller` from `x0` for `steps` steps: returns the true states (k+1, n) and the
    commanded tensions (k,), k = steps unless the state would leave the domain: then the loop
    halts there, as the simulator does, and k < steps.

    `plant`: plant parameters making the true plant differ from the model: a mapping (e.g.
    `tsr_sim.plant.plant_parameters('actuator_weak')`, with `mass`, `orbit_rate`,
    `tether_length` for its units) or a plant variant's name or file; `scale`: the units the
    controller converts with (default: the paper's, `Scale()`); `excitation`: a
    `control.excitation.Excitation` added to the law's tension before the clamp, as the
    controller node adds it (reset here); `compute_seconds`: a list the wall time of every
    compute() call is appended to (the node times the same call).
    """
    if isinstance(steps, bool) or not isinstance(steps, numbers.Integral) or steps < 0:
        raise ValueError(f'closed_loop: steps must be an integer >= 0, got {steps!r}')
    if abs(controller.h - h) > 1e-12 * h:
        raise ValueError(f'closed_loop: {controller.name} was built for h = {controller.h:g} '
                         f'tau, the loop steps h = {h:g}')
    if isinstance(plant, str):
        plant = plant_parameters(plant)
    elif plant is not None and not isinstance(plant, Mapping):
        raise ValueError('closed_loop: plant must be a mapping of plant parameters or a plant '
                         f'variant name, got {type(plant).__name__}')
    scale = scale or Scale()
    params = dict(plant or {}, initial_state=[float(v) for v in x0], step=h, substeps=substeps)
    sim = Plant(config_from_parameters(params, scale))
    plant_scale = sim.config.scale
    step = ControlStep(controller, TensionLimiter(u_max), excitation)
    step.reset()
    states, tensions = [sim.state.copy()], []
    for _ in range(steps):
        measured = scale.state_from_si(plant_scale.state_to_si(sim.measure()))
        result = step(measured)
        if compute_seconds is not None:
            compute_seconds.append(result.compute_seconds)
        if result.outcome in (Outcome.NON_FINITE_OUTPUT, Outcome.NON_FINITE_STATE,
                              Outcome.REFUSED_STATE):
            raise ValueError(f'{controller.name} gave no tension at step {len(tensions)}: '
                             f'{result.outcome.name.lower()}')
        u = result.tension
        tension = scale.u_to_tension(u)
        if sim.accept(tension) is not None:
            raise ValueError(f'the plant refused the clamped tension {tension} N')
        sim.advance(tension)
        if sim.status is Status.HALTED_OUT_OF_DOMAIN:
            break
        tensions.append(u)
        states.append(sim.state.copy())
    return np.array(states), np.array(tensions)
