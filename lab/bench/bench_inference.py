"""Per-step compute of every controller, and the lifted model in numpy against torch.

Figures (microseconds, median and p99 over `--repeats` calls on states along a deployment):
- psi_x + psi_u for one state: numpy (`model.LiftedModel`, the controller's form) and torch
  (`learning.deep_koopman.DeepKoopman`, the training form); the ratio torch / numpy.
- compute(x) of each controller: linear_lqr, fractional_pd, koopman_lqr, koopman_mpc (the
  last is one OSQP solve per step: the MPC solve time).
"""

import argparse
import os
import sys
import time

import numpy as np
import torch

from tsr_koopman_ctrl.control import closed_loop, LinearisedLqr, make_controller
from tsr_koopman_ctrl.learning import deep_koopman
from tsr_koopman_ctrl.model import DEFAULT_MODEL, LiftedModel, model_file, resolve
from tsr_sim import dynamics

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402


def timings(function, inputs, repeats):
    times = []
    for i in range(repeats):
        x = inputs[i % len(inputs)]
        start = time.perf_counter()
        function(x)
        times.append(time.perf_counter() - start)
    times = np.array(times[len(times) // 10:]) * 1e6   # drop the warm-up tenth
    return np.median(times), np.percentile(times, 99)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--model', default=DEFAULT_MODEL)
    parser.add_argument('--repeats', type=int, default=3000)
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    torch.set_num_threads(1)
    states, _ = closed_loop(LinearisedLqr(), dynamics.PAPER_INITIAL_STATE, 1000)
    model = LiftedModel.load(args.model)
    tensors, config, _ = model_file.load(resolve(args.model))
    net = deep_koopman.DeepKoopman.from_numpy(tensors, config).eval()

    def numpy_lift(x):
        return model.psi_x(x), model.psi_u(x, 3.0)

    def torch_lift(x):
        with torch.no_grad():
            t = torch.as_tensor(x, dtype=torch.float32)[None]
            return net.psi_x(t), net.psi_u(t, torch.tensor([3.0]))

    rows = []
    for name, function in (('psi_x + psi_u, numpy', numpy_lift),
                           ('psi_x + psi_u, torch', torch_lift)):
        rows.append((name, *timings(function, states, args.repeats)))
    ratio = rows[1][1] / rows[0][1]
    for name in ('linear_lqr', 'fractional_pd', 'koopman_lqr', 'koopman_mpc'):
        options = {'model': model} if name.startswith('koopman') else {}
        controller = make_controller(name, **options)
        rows.append((f'{name} compute', *timings(controller.compute, states,
                                                 max(300, args.repeats // 5))))
    say(f"{'what':32s} {'median us':>10s} {'p99 us':>10s}")
    for name, median, p99 in rows:
        say(f'{name:32s} {median:10.1f} {p99:10.1f}')
    say(f'torch / numpy (median) for the lifting: {ratio:.1f}x')
    say.publish()


if __name__ == '__main__':
    main()
