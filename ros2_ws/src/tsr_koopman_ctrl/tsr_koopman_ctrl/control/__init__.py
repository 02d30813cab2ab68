"""Tension laws, ROS-free, one module each, behind one interface (`law.Law`).

    from tsr_koopman_ctrl.control import make_controller, TensionLimiter
    law = make_controller('koopman_mpc', horizon=5)       # settings by keyword; offset-free
                                                          # (observer) unless observer=
                                                          # ObserverSettings(disturbance='none')
    limiter = TensionLimiter(5.0)
    law.reset()
    u = limiter(law.compute(x))                           # dimensionless state -> tension

Every law's settings are declared once, in its module (`settings.py` says how node parameters,
CLI flags and config files derive from them).
"""

from tsr_koopman_ctrl.control.fractional_pd import FractionalOrderPd  # noqa: F401
from tsr_koopman_ctrl.control.koopman_lqr import KoopmanLqr  # noqa: F401
from tsr_koopman_ctrl.control.koopman_mpc import KoopmanMpc  # noqa: F401
from tsr_koopman_ctrl.control.nmpc import KoopmanNmpc, PhysicsNmpc  # noqa: F401
from tsr_koopman_ctrl.control.limiter import TensionLimiter  # noqa: F401
from tsr_koopman_ctrl.control.linear_lqr import LinearisedLqr  # noqa: F401
from tsr_koopman_ctrl.control.loop import closed_loop  # noqa: F401
from tsr_koopman_ctrl.control.offset_free import ObserverSettings, OffsetFree  # noqa: F401
from tsr_koopman_ctrl.control.registry import CONTROLLERS, make_controller  # noqa: F401
