"""Tune a law's settings with Optuna, the same way for every law, and score it on held-out starts.

    python -m lab.tune --law linear_lqr [--trials 60] [--jobs 2]
        [--storage out/tune/linear_lqr.journal | postgresql://...] [--swing-max 0.8]
        [--fix SETTING=VALUE] [--also SETTING] [--objective settle|ratio|worst-ratio|swing]
        [--penalty flat|graded] [--starts comparison|swing]

The search space is each setting's `tune` entry in its law's Settings class (the one declaration).
A trial closes the law on the dynamics module (step-identical to the DDS loop) from every tuning
start (`evaluation.starts.COMPARISON_STARTS`; with `--starts swing` also `SWING_TUNING_STARTS`, two
starts with an initial swing like the held-out ones) and scores, per --objective, the mean settle
time into the 1% zone ('settle', the default), the mean frontier ratio ('ratio': settle time over
the minimum time at the run's own swing, `evaluation.frontier`, so a law gains nothing by swinging
wider), the largest frontier ratio ('worst-ratio': the issue's targets are "from every start") or
the largest swing ('swing': can any setting hold a bound at all); a start that does not settle,
halts, or swings beyond --swing-max scores PENALTY_TAU (settle) or PENALTY_RATIO, flat by default;
with `--penalty graded` the penalty grows with how far the run missed (radians past the swing
bound, plus one if it did not settle), so a search whose first trials all miss still learns which
way is better. A study that never scored under the penalty says so in its report. A study keeps the
objective, the penalty and the tuning starts it was started with. The law's own settings are the
first trial, so tuning never reports worse than the default. The study lives in Optuna's storage: a
journal file here (several processes share it: --jobs starts them; a second command with another
--seed adds workers), or a database URL (`postgresql://user:password@host:port/db`: several
machines on one study, docs/tuning.md); running the command again resumes it up to --trials in
total. At the end the best settings are scored on the held-out starts
(`HELD_OUT_STARTS`), which the tuning never saw, in --jobs processes, and written to
<out>/<study>.json and .md.
`--fix` holds a setting out of the search: koopman_lqr's q only counts with state_weight
'state', and a joint search samples that form a few times only (4 of 60 trials, docs/tuning.md).
`--also` adds a setting the default search leaves out: `q_cross`, the cross terms of the
quadratic-cost laws' state weight (six more dimensions).
"""

import argparse
import sys

from tsr_koopman_ctrl.control import CONTROLLERS
from tsr_koopman_ctrl import arguments
from lab.tuning import tune
from lab.tuning.run import Interrupted, OUT
from lab.tuning.scoring import OBJECTIVES, TUNING_STARTS
from lab.tuning.storage import shown


def parser():
    p = argparse.ArgumentParser(prog='tune', description=__doc__.split('\n\n')[0])
    p.add_argument('--law', required=True, choices=sorted(CONTROLLERS))
    p.add_argument('--trials', type=arguments.integer(1), default=60,
                   help='finished trials in the study')
    p.add_argument('--jobs', type=arguments.integer(1), default=1,
                   help='worker processes on the study (and for its final report)')
    p.add_argument('--storage', help='journal file or database URL, e.g. '
                   'postgresql://user:password@host:port/db (default: <out>/<study>.journal)')
    p.add_argument('--study', help='study name (default: <law>[_<fixed settings>]'
                   '[_<objective>]_swing<swing-max>)')
    p.add_argument('--objective', choices=sorted(OBJECTIVES), default='settle',
                   help="what a trial minimises over the tuning starts: mean settle time, mean "
                   "or largest frontier ratio at the run's own swing, or the largest swing "
                   "(a run that does not settle scores the penalty)")
    p.add_argument('--penalty', choices=('flat', 'graded'), default='flat',
                   help="a start that misses (does not settle, swings past --swing-max) "
                   "scores the penalty ('flat') or the penalty plus how far it missed: radians "
                   "past the bound, plus one if it did not settle ('graded')")
    p.add_argument('--starts', choices=sorted(TUNING_STARTS), default='comparison',
                   help="the tuning starts: the four comparison starts ('comparison'), or those "
                   "and two with an initial swing ('swing'); the held-out starts never")
    p.add_argument('--swing-max', type=arguments.number(above=0), default=0.8,
                   help='largest |theta| a run may reach and still count as settled [rad]')
    p.add_argument('--steps', type=arguments.STEPS, default=2000)
    p.add_argument('--seed', type=arguments.SEED, default=0)
    p.add_argument('--out', default=OUT, type=arguments.output_dir)
    p.add_argument('--fix', action='append', default=[], metavar='SETTING=VALUE',
                   help='hold a setting at a value instead of tuning it (repeatable; e.g. '
                   'state_weight=state for koopman_lqr)')
    p.add_argument('--also', action='append', default=[], metavar='SETTING',
                   help='search a setting that is left out by default (repeatable; e.g. '
                   "q_cross: the state weight's cross terms)")
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    options = {name: getattr(args, name) for name in (
        'trials', 'jobs', 'storage', 'study', 'objective', 'penalty', 'starts', 'swing_max',
        'steps', 'seed', 'out', 'fix', 'also')}
    try:
        result = tune(args.law, **options)
    except ValueError as error:         # refused before any trial ran
        print(f'tune: {error}', file=sys.stderr)
        return 2
    except Interrupted as stop:
        print(f'tune: interrupted; {shown(stop.storage)} keeps the finished trials: the same '
              'command resumes the study', file=sys.stderr)
        return arguments.INTERRUPTED_STATUS
    except RuntimeError as error:
        print(f'tune: {error}', file=sys.stderr)
        return 1
    print(result.text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
