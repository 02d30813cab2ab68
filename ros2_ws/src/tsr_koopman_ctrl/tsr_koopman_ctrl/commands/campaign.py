"""Monte Carlo campaigns: dispersed runs of one or more laws, ROS-free, on Dask distributed.

    ros2 run tsr_koopman_ctrl campaign [--spec FILE] [--law NAME ...] [--runs N] [--steps K]
        [--seed S] [--set SECTION.SETTING=VALUE ...] [--plant VARIANT] [--swing-limit RAD]
        [--workers N | --address ADDR] [--out DIR] [--resume]
    ros2 run tsr_koopman_ctrl campaign report DIR
    ros2 run tsr_koopman_ctrl campaign replay DIR --run N --law LABEL

The flags override the spec file's values (`--set` adds to its `set`); the spec's format is in
`tsr_koopman_ctrl.campaign.spec`. Each finished run is a row kept at once under DIR/rows/;
DIR/runs.parquet holds them all and DIR/report.md reports them at the end. `--resume` flies
only the runs DIR lacks. `replay` flies one run again here and checks it against its row
(exit 1 if they differ). Exit status 2 for a bad spec or option (one line, before any run).
"""

import argparse
import sys

from tsr_koopman_ctrl.commands import cli
from tsr_koopman_ctrl.control import CONTROLLERS

SUBCOMMANDS = ('report', 'replay')


def campaign_parser():
    parser = argparse.ArgumentParser(prog='campaign', description=__doc__.split('\n\n')[0],
                                     epilog='Also: campaign report DIR; campaign replay DIR '
                                     '--run N --law LABEL.')
    parser.add_argument('--spec', help='a YAML spec file (tsr_koopman_ctrl.campaign.spec)')
    parser.add_argument('--law', nargs='+', choices=sorted(CONTROLLERS),
                        help="the laws flown on every case (replaces the spec's laws)")
    parser.add_argument('--runs', type=cli.integer(1), help="runs (default: the spec's starts "
                        'x its plant cases; a start box counts 100 starts)')
    parser.add_argument('--steps', type=cli.STEPS, help='steps of h = 0.01 tau (default 1500)')
    parser.add_argument('--seed', type=cli.SEED, help='the campaign seed (default 0): every '
                        "run's values come from (seed, run)")
    parser.add_argument('--set', action='append', metavar='SECTION.SETTING=VALUE',
                        help='a setting, as deploy --set takes it, for every law it applies '
                        'to; repeatable')
    parser.add_argument('--plant', help='a named plant variant the plant starts from '
                        '(tsr_sim/config/plants: actuator_weak, heavy_robot, ...)')
    parser.add_argument('--swing-limit', type=cli.number(above=0), metavar='RAD',
                        help='a run swinging past it fails')
    engine = parser.add_mutually_exclusive_group()
    engine.add_argument('--workers', type=cli.integer(1), help='local cluster: worker '
                        'processes, one thread each (default: one per core)')
    engine.add_argument('--address', help="a running Dask scheduler's address "
                        '(tcp://host:8786): the cluster behind it flies the runs')
    parser.add_argument('--out', default='out/campaign', type=cli.output_dir,
                        help='the campaign directory (default out/campaign)')
    parser.add_argument('--resume', action='store_true', help='complete the campaign in --out '
                        '(the same spec; without a spec or flags, the one stored there)')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    return parser


def overrides(args):
    return {'runs': args.runs, 'steps': args.steps, 'seed': args.seed, 'laws': args.law,
            'set': args.set, 'variant': args.plant, 'swing_limit': args.swing_limit}


def parse_args(argv):
    from tsr_koopman_ctrl.campaign import Campaign, load_spec
    from tsr_koopman_ctrl.campaign.rows import read_spec
    parser = campaign_parser()
    args = parser.parse_args(argv)
    try:
        given = args.spec is not None or any(v is not None for v in overrides(args).values())
        if args.resume and not given:
            spec = read_spec(args.out)
            if spec is None:
                raise ValueError(f'--resume: {args.out} holds no campaign (spec.yaml)')
            args.campaign = Campaign.parse(spec, where=f'{args.out}/spec.yaml')
        else:
            args.campaign = load_spec(args.spec, **overrides(args))
        from tsr_koopman_ctrl.campaign.engine import prepare
        prepare(args.campaign, args.out, args.resume)
    except ValueError as error:
        parser.error(str(error))
    return args


def report_main(argv):
    from tsr_koopman_ctrl.campaign import report
    parser = argparse.ArgumentParser(prog='campaign report',
                                     description="A campaign directory's report.md and figures.")
    parser.add_argument('dir', help='the campaign directory')
    args = parser.parse_args(argv)
    try:
        print(report(args.dir))
    except ValueError as error:
        parser.error(str(error))
    print(f'[campaign] report in {args.dir}/report.md', flush=True)
    return 0


def replay_main(argv):
    from tsr_koopman_ctrl.campaign import differences, replay
    parser = argparse.ArgumentParser(prog='campaign replay', description='One run of a '
                                     'campaign flown again here, ROS-free, against its row.')
    parser.add_argument('dir', help='the campaign directory')
    parser.add_argument('--run', type=cli.integer(0), required=True)
    parser.add_argument('--law', required=True, help="the law's label in the campaign")
    args = parser.parse_args(argv)
    try:
        row, stored = replay(args.dir, args.run, args.law)
    except ValueError as error:
        parser.error(str(error))
    for key, value in row.items():
        print(f'{key}: ' + (f'({len(value)} samples)' if isinstance(value, list) else f'{value}'))
    if stored is None:
        print('[campaign] the campaign has no row for this run yet', flush=True)
        return 0
    differ = differences(row, stored)
    if differ:
        print(f'[campaign] differs from its row in {", ".join(differ)}', file=sys.stderr)
        return 1
    print('[campaign] equal to its row (timing columns aside)', flush=True)
    return 0


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == 'report':
        return report_main(argv[1:])
    if argv and argv[0] == 'replay':
        return replay_main(argv[1:])
    from tsr_koopman_ctrl.campaign import CampaignError, run_campaign
    args = parse_args(argv)
    try:
        rows = run_campaign(args.campaign, args.out, workers=args.workers,
                            address=args.address, resume=True, progress=not args.no_progress)
    except KeyboardInterrupt:
        print(f'[campaign] interrupted: the finished runs are in {args.out}/rows; --resume '
              'completes it', file=sys.stderr)
        return cli.INTERRUPTED_STATUS
    except CampaignError as error:
        print(f'[campaign] {error}', file=sys.stderr)
        return 1
    print(f'[campaign] {len(rows)} rows in {args.out}/runs.parquet; report in '
          f'{args.out}/report.md', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
