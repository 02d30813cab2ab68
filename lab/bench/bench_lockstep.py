"""Lockstep closed-loop steps per second over DDS: simulator and controller as two processes.

Runs a deployment as the main job does (sim, controller, recorder) for --steps steps, with the
main job's law unless --law says otherwise, and reads the rate off the bag: steps between the
first and last state message divided by the span of their publish times (the simulator's wall
clock; the log times are sim time, as rosbag2 records on sim time).
"""

import argparse
import os
import sys
import tempfile

from tsr_sim.wire import resolve, STATE_TOPIC

from tsr_koopman_ctrl.bag import BagReader
from tsr_koopman_ctrl.control.registry import DEFAULT_LAW, parse_assignments
from tsr_koopman_ctrl.deployment import Deployment

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402


#: The transport alone: linear_lqr without an observer computes in ~2 us a step.
TRANSPORT = ('linear_lqr', ['observer.disturbance=none'])


def lockstep(law, settings, steps):
    """(steps, seconds between the first and the last state published) of a deployment."""
    with tempfile.TemporaryDirectory() as tmp:
        run = Deployment(law, settings, steps=steps, bags=os.path.join(tmp, 'bags'),
                         logs=os.path.join(tmp, 'logs')).run()
        if run.halted:
            raise SystemExit(f'deployment of {law} failed: the state left the model domain')
        times = [m.publish_time_ns
                 for m in BagReader(run.bag).messages({resolve(STATE_TOPIC)})]
    return len(times) - 1, (times[-1] - times[0]) * 1e-9


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--steps', type=int, default=3000)
    parser.add_argument('--law', default=DEFAULT_LAW,
                        help=f"the law (default {DEFAULT_LAW}, the main job's); linear_lqr with "
                        "--set observer.disturbance=none (~2 us per step) measures the "
                        'transport alone')
    parser.add_argument('--set', action='append', default=[], metavar='LAW.SETTING=VALUE',
                        help='a controller setting, as deploy --set')
    parser.add_argument('--no-baseline', action='store_true',
                        help='skip the comparison run: linear_lqr without an observer, the '
                        'transport alone')
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    try:
        parse_assignments(args.set)         # a bad one is one line, before any run
    except ValueError as error:
        parser.error(str(error))
    runs = [(args.law, args.set)]
    if not args.no_baseline and (args.law, args.set) != TRANSPORT:
        runs.append(TRANSPORT)
    rates = []
    for law, assignments in runs:
        steps, span = lockstep(law, parse_assignments(assignments), args.steps)
        shown = ' '.join(assignments)
        rates.append(steps / span)
        say(f'lockstep over DDS ({law}{", " if shown else ""}{shown}): '
            f'{steps} steps in {span:.2f} s = {steps / span:,.0f} steps/s '
            f'({span / steps * 1e3:.2f} ms per state -> command -> state round trip)')
    if len(rates) > 1:
        say(f'ratio {args.law} / the transport alone: {rates[0] / rates[1]:.2f}')
    say.publish()


if __name__ == '__main__':
    main()
