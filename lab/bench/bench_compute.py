"""Controller compute time per step of every law in the registry, physics_nmpc included.

Each law flies its own closed loop (`control.closed_loop`, the ROS-free loop) from the paper's
start for `--steps` steps, and every compute(x) call is timed there: an optimising law's time
depends on its own trajectory and warm starts, so states replayed from another law's loop would
not measure it. Figures (microseconds): median, p99 and max per step, the median as a fraction
of the control period h = 0.01 tau (8.47 s of flight at the paper's orbit rate) and as a
multiple of linear_lqr's. The bare laws by default (no observer, no supervisor);
--offset-free builds each as the controller node does: in the disturbance observer, a learned
law under its runtime-assurance supervisor beside its fallback. The laws' defaults, or a settings
preset (--preset tuned_settle: koopman_mpc plans 3 steps there, against 30 by default). The
first build of a law (a model loaded, a CasADi function made) is not
timed.
"""

import argparse
import os
import sys

import numpy as np
from tsr_sim import dynamics
from tsr_sim.units import Scale

from tsr_koopman_ctrl.control import closed_loop, CONTROLLERS, make_controller
from tsr_koopman_ctrl.control.registry import preset
from tsr_koopman_ctrl.evaluation import PAPER_START

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--steps', type=int, default=500)
    parser.add_argument('--law', nargs='+', default=list(CONTROLLERS), choices=list(CONTROLLERS))
    parser.add_argument('--offset-free', action='store_true',
                        help='each law as the node builds it: in the disturbance observer, a '
                        'learned law under its supervisor')
    parser.add_argument('--preset', help="settings preset, by path or by name under config/ "
                        "('untuned', 'tuned_settle', 'tuned_cross'; default: the laws' defaults)")
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    try:
        settings = preset(args.preset) if args.preset else {}
    except ValueError as error:
        parser.error(str(error))
    wrappers = {} if args.offset_free else {'observer': 'none', 'supervisor': 'none',
                                            'safety': 'none'}
    h = dynamics.PAPER_STEP
    period_us = Scale().tau_to_seconds(h) * 1e6   # of flight, at the paper's orbit rate
    rows = []
    for name in args.law:
        law, seconds = make_controller(name, **wrappers, **settings.get(name, {})), []
        closed_loop(law, PAPER_START, args.steps, compute_seconds=seconds)
        times = np.array(seconds) * 1e6
        rows.append((name, np.median(times), np.percentile(times, 99), times.max(),
                     law.fallbacks))
    base = next((r[1] for r in rows if r[0] == 'linear_lqr'), None)
    kind = ('laws as deployed (offset-free, learned laws supervised and filtered)'
            if args.offset_free
            else 'bare laws')
    say(f"{args.steps} steps from the paper start, {kind}, "
        f"{args.preset or 'default'} settings; h = {h} tau = "
        f'{period_us / 1e6:.2f} s')
    say(f"{'law':16s} {'median us':>10s} {'p99 us':>10s} {'max us':>10s} "
        f"{'median / h':>11s} {'p99 / h':>9s} {'x linear_lqr':>13s} {'fallbacks':>9s}")
    for name, median, p99, worst, fallbacks in rows:
        versus = f'{median / base:13.1f}' if base else f"{'-':>13s}"
        say(f'{name:16s} {median:10.1f} {p99:10.1f} {worst:10.1f} '
            f'{median / period_us:11.2e} {p99 / period_us:9.2e} {versus} {fallbacks:9d}')
    say.publish()


if __name__ == '__main__':
    main()
