"""What a benchmark prints, kept: written to --out and into its docs page (--page) between the
markers named after --out, with the date, the machine and the command, so that
docs/benchmarks.md shows the run that made its figures.

    say = Printed(parser, args)       # after parse_args; checks the page before any work
    say('figure ...')                 # printed as print() would, and kept
    say.publish()                     # at the end: --out and --page written
"""

import os
import shlex
import sys

from lab.report import check_page, stamp, write_into_page


def add_options(parser):
    parser.add_argument('--out', default='', help='also write what is printed to this file')
    parser.add_argument('--page', default='', help='a docs page to write what is printed '
                        'into, between the markers named after --out (its name without the '
                        'suffix)')


def marker(out):
    """The page markers a run writes between: its --out file's name without the suffix."""
    return os.path.splitext(os.path.basename(out))[0]


class Printed:
    """print() that keeps its lines for --out and --page."""

    def __init__(self, parser, args):
        self.out, self.page, self.lines = args.out, args.page, []
        if self.page:
            if not self.out:
                parser.error('--page needs --out (the markers are named after it)')
            try:
                check_page(self.page, marker(self.out))
            except ValueError as error:
                parser.error(str(error))

    def __call__(self, text=''):
        print(text, flush=True)
        self.lines.extend(str(text).split('\n'))

    def publish(self):
        text = '\n'.join(self.lines).strip('\n') + '\n'
        if self.out:
            os.makedirs(os.path.dirname(os.path.abspath(self.out)), exist_ok=True)
            with open(self.out, 'w') as f:
                f.write(text)
        if self.page:
            command = ' '.join(['python'] + [shlex.quote(word) for word in sys.argv])
            threads = os.environ.get('OMP_NUM_THREADS')
            if threads:
                command = f'OMP_NUM_THREADS={threads} {command}'
            write_into_page(self.page, marker(self.out),
                            f'{stamp()}: `{command}`\n\n```text\n{text}```\n')
