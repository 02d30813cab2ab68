"""Lockstep closed-loop steps per second over DDS: simulator and controller as two processes.

Runs a deployment as the main job does (sim, controller, recorder) for --steps steps, with the
main job's law unless --law says otherwise, and reads the rate off the bag: steps between the
first and last state message divided by the span of their publish times (the simulator's wall
clock; the log times are sim time, as rosbag2 records on sim time).
"""

import argparse
import os
import tempfile

from tsr_sim.wire import resolve, STATE_TOPIC

from tsr_koopman_ctrl.bag import BagReader
from tsr_koopman_ctrl.control.registry import DEFAULT_LAW
from tsr_koopman_ctrl.control.settings import parse_assignments
from tsr_koopman_ctrl.deployment import Deployment


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--steps', type=int, default=3000)
    parser.add_argument('--law', default=DEFAULT_LAW,
                        help=f"the law (default {DEFAULT_LAW}, the main job's); linear_lqr with "
                        "--set observer.disturbance=none (~2 us per step) measures the "
                        'transport alone')
    parser.add_argument('--set', action='append', default=[], metavar='LAW.SETTING=VALUE',
                        help='a controller setting, as deploy --set')
    args = parser.parse_args()
    try:
        settings = parse_assignments(args.set)
    except ValueError as error:
        parser.error(str(error))
    with tempfile.TemporaryDirectory() as tmp:
        run = Deployment(args.law, settings, steps=args.steps, bags=os.path.join(tmp, 'bags'),
                         logs=os.path.join(tmp, 'logs')).run()
        if run.halted:
            raise SystemExit('deployment failed: the state left the model domain')
        times = [m.publish_time_ns
                 for m in BagReader(run.bag).messages({resolve(STATE_TOPIC)})]
    span = (times[-1] - times[0]) * 1e-9
    print(f'lockstep over DDS ({args.law}{", " if args.set else ""}{" ".join(args.set)}): '
          f'{len(times) - 1} steps in {span:.2f} s = '
          f'{(len(times) - 1) / span:,.0f} steps/s '
          f'({span / (len(times) - 1) * 1e3:.2f} ms per state -> command -> state round trip)')


if __name__ == '__main__':
    main()
