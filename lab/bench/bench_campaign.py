"""Campaign throughput on Dask distributed: the same campaign with 1 and with 2 local workers in
one run, and the engine's overhead against the runs' own compute.

Each worker count gets a fresh local cluster (its start-up timed apart); the campaign's wall
time runs from the first submission to the last row kept on disk. Throughput: runs per wall
second; the ratio, 2 workers over 1 (target >= 1.8). Overhead: the workers' wall time not
spent flying runs, (workers x wall - sum of the runs' own seconds, timed inside each task) /
that sum (target <= 5%): scheduling, pickling, the driver's row files and the campaign's tail
(a worker idle while the last run ends) all count against it.
"""

import argparse
import os
import sys
import tempfile
import time

# Run as a script (python lab/bench/<name>.py): the repository root on the path, for lab/.
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from lab.bench.printed import add_options, Printed  # noqa: E402


def main():
    from dask.distributed import Client, LocalCluster

    from tsr_koopman_ctrl.campaign import Campaign, fly, run_campaign
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=40)
    parser.add_argument('--steps', type=int, default=1000)
    parser.add_argument('--law', default='koopman_lqr')
    add_options(parser)
    args = parser.parse_args()
    say = Printed(parser, args)
    campaign = Campaign.parse({
        'runs': args.runs, 'steps': args.steps, 'seed': 1, 'laws': [args.law],
        'start': {'low': [-0.05, -0.1, -0.995, 0.3], 'high': [0.05, 0.1, -0.98, 0.7]},
        'plant': {'actuator_gain': {'low': 0.8, 'high': 1.2}}})
    say(f'{args.runs} runs of {args.law} (its default build), {args.steps} steps each, dispersed '
        f'start and actuator gain; {os.cpu_count()} cores')
    say(f"{'workers':>7s} {'start-up s':>10s} {'wall s':>8s} {'runs/s':>7s} "
        f"{'run compute s':>13s} {'overhead':>8s}")
    throughput = {}
    for workers in (1, 2):
        began = time.perf_counter()
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                          dashboard_address=':0') as cluster, Client(cluster) as client:
            client.wait_for_workers(workers)
            startup = time.perf_counter() - began
            # Each worker's first run loads the model and builds its law's functions: paid once
            # a worker, warmed here so that both counts measure the campaign alone.
            client.run(fly, campaign, 0, campaign.laws[0].label)
            with tempfile.TemporaryDirectory() as out:
                began = time.perf_counter()
                rows = run_campaign(campaign, os.path.join(out, 'c'), client=client,
                                    progress=False, report=False)
                wall = time.perf_counter() - began
        compute = float(rows['run_seconds'].sum())
        throughput[workers] = len(rows) / wall
        overhead = (workers * wall - compute) / compute
        say(f'{workers:7d} {startup:10.2f} {wall:8.2f} {throughput[workers]:7.2f} '
            f'{compute:13.2f} {overhead:8.1%}')
    say(f'throughput 2 workers / 1 worker: {throughput[2] / throughput[1]:.2f}x '
        '(target >= 1.8x)')
    say.publish()


if __name__ == '__main__':
    main()
