"""The controller node's own parameters, declared once as a schema class (`tsr_sim.schema`),
ROS-free. Beside them the node declares every settings section (`registry.settings_sections`:
the laws', the observer's, ...) as `<section>.<setting>` and the units (`ScaleSettings`), all
read at configure, and the process parameters every node gets."""

import dataclasses

from tsr_sim import dynamics
from tsr_sim.schema import AT_CONFIGURE, LIVE, setting, Settings
from tsr_sim.units import Scale

from tsr_koopman_ctrl.control.registry import CONTROLLERS, DEFAULT_LAW


@dataclasses.dataclass(frozen=True)
class ControllerNodeSettings(Settings):
    """`autostart` is read at start, `law` at configure; the rest are applied when set."""

    autostart: bool = setting(True, 'configure and activate at start (false: wait for a '
                              'lifecycle manager)')
    law: str = setting(DEFAULT_LAW, f'control law: one of {sorted(CONTROLLERS)} (read at '
                       'configure)', applied=AT_CONFIGURE)
    max_tension: float = setting(Scale().u_to_tension(dynamics.TENSION_LIMIT),
                                 f'output clamp [N] (default: u = {dynamics.TENSION_LIMIT:g} at '
                                 'the default units)', low=1e-9, high=1e9, applied=LIVE)
    safe_tension: float = setting(Scale().u_to_tension(dynamics.EQUILIBRIUM_TENSION),
                                  'the tension of the stop command (sent on deactivate, '
                                  'shutdown and when no state arrives for state_timeout) for a '
                                  'plant without a hold of its own [N] (default: u = 3 at the '
                                  'default units, which holds the deployed equilibrium)',
                                  low=0.0, high=1e9, applied=LIVE)
    state_timeout: float = setting(5.0, 'wall seconds without a state before the stop command '
                                   'is sent', low=0.01, high=3600.0, applied=LIVE)
    wait_for_subscribers: int = setting(0, 'answer no state until this many readers of the '
                                        'tension commands have matched (simulator, recorder)',
                                        low=0, high=1000, applied=LIVE)
    wait_for_status_subscribers: int = setting(0, 'answer no state until this many readers of '
                                               'the controller status (and excitation) have '
                                               'matched (a recorder)', low=0, high=1000,
                                               applied=LIVE)
