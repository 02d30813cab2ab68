"""Bags on the command line: what a bag holds, the runs of its loop, and a complete bag from
one a crash left open.

    python -m tsr_koopman_ctrl.commands.bag info BAG
    python -m tsr_koopman_ctrl.commands.bag runs BAG [--namespace NS] [--sample-period S] ...
    python -m tsr_koopman_ctrl.commands.bag recover BAG [--out DIR | --in-place]
    (installed as `bag`: ros2 run tsr_koopman_ctrl bag info BAG)

`info` prints the files with their state, every topic with its type and count, start and
duration, and what metadata.yaml says; `runs` the loop's units, sample period and command
matching (a bag needs only tsr/state and tsr/tension_cmd; one without the simulator's RunInfo
is read with the options given, as `retrain` takes them), then one line per run; `recover` one
line: messages kept per topic, and from which files. What each does: `bag.files`, their API.
Errors: one line, exit status 2.
"""

import argparse
import sys

from tsr_koopman_ctrl.bag.files import info, recover, runs
from tsr_koopman_ctrl.commands import cli


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        self.exit(2, f'{self.prog}: {message} ({self.prog} --help)\n')   # one line, no usage


def parser():
    p = _Parser(prog='bag', description=__doc__.split('\n\n')[0])
    commands = p.add_subparsers(dest='command', required=True)
    info_cmd = commands.add_parser('info', help='files, topics, counts, duration, file states')
    info_cmd.add_argument('bag', help='bag directory or one .mcap file')
    runs_cmd = commands.add_parser(
        'runs', help='the runs of the loop, its units, sample period and command matching')
    runs_cmd.add_argument('bag', help='bag directory or one .mcap file')
    runs_cmd.add_argument('--namespace', help='the loop to read in a bag holding several')
    cli.add_loop_reading(runs_cmd)
    rec = commands.add_parser('recover', help='a complete, indexed bag from a killed one')
    rec.add_argument('bag', help='bag directory')
    where = rec.add_mutually_exclusive_group()
    where.add_argument('--out', help='output bag directory (default: <BAG>_recovered)')
    where.add_argument('--in-place', action='store_true',
                       help="replace the bag's files (through a temporary directory)")
    return p


def main(argv=None):
    try:
        args = parser().parse_args(argv)
    except SystemExit as stop:         # argparse: --help (0) or a bad argument (2)
        return stop.code
    try:
        if args.command == 'info':
            print('\n'.join(info(args.bag)))
        elif args.command == 'runs':
            print('\n'.join(runs(args.bag, args.namespace, **cli.loop_reading(args))))
        else:
            print(recover(args.bag, args.out, args.in_place).line())
    except (ValueError, OSError, RuntimeError) as error:
        print(f'bag: {error}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())
