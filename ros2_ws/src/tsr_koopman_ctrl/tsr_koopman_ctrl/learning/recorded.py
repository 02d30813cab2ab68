"""Recorded bags -> training windows, trusting a bag only as far as it can be checked.

    from tsr_koopman_ctrl.bag.checks import find_bags
    from tsr_koopman_ctrl.learning import recorded
    bags = find_bags(['bags/'])                      # a bag, one .mcap file, or every bag below
    windows = recorded.read_windows(bags[0])        # BagWindows: data, provenance, warnings
    data = windows.data                              # Dataset of 30-step windows

A window is T + 1 consecutive states and the T tensions APPLIED between them (`bag.tsr_loop`
matches commands to states): from a lockstep simulator the first command on tsr/tension_cmd
answering each state, matched by the `step` both carry, never by position; from a timed
simulator or hardware the command in force over each sample (a zero-order hold of the commands
as the recorder received them). Either already holds the controller's excitation. States and
tensions are converted to the paper's variables with the units scale the simulator recorded
(RunInfo), else the one given (`scale`, default the paper's). Windows never span a gap: a
missing step, a state without a command, a sample over which the plant held the tether (a
stop), a command the simulator refuses (non-finite, negative, over its `max_tension`), a state
that is non-finite, outside the domain or beyond |x| <= `max_abs_state` (the sampler's runaway
bound), or a step recorded with two different states ends a gap-free run; each run is cut into
windows (one every `stride` steps; by default they do not overlap), and what was skipped is
counted.

A bag needs only tsr/state and tsr/tension_cmd (as hardware writes one). Without the
simulator's RunInfo the units are the ones given, the sample period the one given
(`sample_period` [s]) or else the median interval of the states' header stamps per step, and
a warning line says what was assumed (and how many stamp intervals stray from the period).

A bag that cannot give trustworthy windows raises `BagDataError`, one line naming the bag:
empty; no tsr_msgs/msg/TsrState or TensionCommand messages (wrong types); a TsrState or
TensionCommand recorded with another definition than the installed one (`bag.checks`: by type
hash, else by the normalised definition, so a bag of stock `ros2 bag record` is read; a bag
recorded before TsrState carried its run number is one of these); no sample period (no
RunInfo, no option, stamps that give none); another sample period or state size than asked;
no complete window. A bag holding resets (the simulator's run number, `TsrState.run`) is cut
into its runs, each command matched to its own run's state, and windows come from every run,
with a warning line. A crash-truncated or damaged file is not an error: the reader keeps what
it can recover (`bag.reader`) and a warning line says how much; so do lines for skipped gaps
and for steps answered by differing commands.

Provenance per bag (in the Dataset and `BagWindows.provenance`): path, sha256 of its .mcap
files (concatenated in split order, and per file), sha256 of its recorded messages
(`messages_sha256`: the same for a recovered or re-chunked copy, whose files differ), message
counts per topic, windows cut, gap counts (with `resets` and per run of the loop its steps and
windows, `loop_runs`), the RunInfo (plant, controller, model, excitation), the units scale and
where it came from (`units`), the sample period and where it came from (`h_source`), and how
commands were matched (`match`).
"""

import dataclasses
import json
import math
import os

import numpy as np
from tsr_sim import dynamics, wire

from tsr_koopman_ctrl.bag.checks import BagDataError, content_hash, loop_topics, scan
from tsr_koopman_ctrl.bag.reader import BagReader, COMPLETE
from tsr_koopman_ctrl.bag.tsr_loop import (check_options, GIVEN_PERIOD_TOLERANCE,
                                           H_FROM_OPTION, H_FROM_RUN_INFO, H_FROM_STAMPS,
                                           H_SOURCES, read_runs, UNITS_FROM_RUN_INFO,
                                           UNITS_SOURCES)
from tsr_koopman_ctrl.evaluation.figures import in_zone
from tsr_koopman_ctrl.learning.dataset import concatenate, Dataset

DEFAULT_STEPS = 30
#: A sample period read from the states' stamps matches the model's within this (relative):
#: stamps carry their clock's jitter and rounding, a recorded RunInfo is exact.
STAMPS_PERIOD_TOLERANCE = 1e-3
#: Relative tolerance on the sample period, by where it came from.
PERIOD_TOLERANCES = {H_FROM_RUN_INFO: 1e-9, H_FROM_OPTION: GIVEN_PERIOD_TOLERANCE,
                     H_FROM_STAMPS: STAMPS_PERIOD_TOLERANCE}
#: A stamp interval this far (relative) from the sample period is reported as irregular.
IRREGULAR_INTERVAL = 0.1
#: Same bound as the sampler's (`SamplingConfig.max_abs_state`): states beyond it are runaways.
MAX_ABS_STATE = 10.0


@dataclasses.dataclass
class BagWindows:
    """The windows of one bag, where they came from, and what was recovered or skipped."""

    path: str
    data: Dataset                  # its provenance is [provenance]
    provenance: dict
    warnings: list
    #: Windows set aside for choosing the best epoch (`validation_fraction`), or None: they
    #: share no step with `data`'s windows.
    validation: Dataset = None


def _json(value):
    """As a JSON file stores it (RunInfo YAML may hold anything YAML can)."""
    return json.loads(json.dumps(value, default=str))


def _runs(link):
    """(start, length) of every run of True in a boolean array."""
    padded = np.r_[False, link, False].astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[::2].tolist(), (edges[1::2] - edges[::2]).tolist()))


def validation_blocks(runs, steps, fraction, offset=0):
    """(first, end) step ranges set aside for validation: each gap-free run is cut into blocks
    of 3 windows and every round(1 / fraction)-th block is held out, the first being block
    `offset` mod that period (a bag's index): the bags of a set give up different phases of
    their deployments, the transient at the start among them, not only the settled end."""
    if fraction <= 0.0:
        return []
    block, period = 3 * steps, max(2, round(1.0 / fraction))
    return [(start + j * block, start + (j + 1) * block) for start, length in runs
            for j in range(length // block) if (j - offset) % period == 0]


def read_windows(path, steps=DEFAULT_STEPS, namespace=None, h=None, state_dim=None,
                 max_abs_state=MAX_ABS_STATE, stride=None, validation_fraction=0.0,
                 validation_offset=0, scale=None, sample_period=None, match=None):
    """Cut one bag into `steps`-step windows, with every check (module docstring).

    A window starts every `stride` steps of a gap-free run (default `steps`: windows that do not
    overlap). Overlapping windows (stride < steps) show the model every phase of a deployment,
    which fine-tuning on a few bags needs (docs/data_loop.md measures it); errors are reported
    on non-overlapping windows. `validation_fraction` > 0 sets blocks of every run aside
    (`validation_blocks`) as non-overlapping validation windows (`BagWindows.validation`); no
    training window touches them, so overlapping windows cannot leak into the epoch choice.

    `h` and `state_dim`, when given, are what the windows must have (the model's); a bag with
    another sample period (`PERIOD_TOLERANCES`: a RunInfo's exactly, a `sample_period` given
    within 0.01%, the stamps' within 0.1%) or state size is refused. `scale`, `sample_period`
    [s] and `match` are `bag.read_runs`'s: the units and sample period of a bag without a
    simulator RunInfo (hardware's), and how its commands are matched to its states. Returns
    BagWindows; raises BagDataError (ValueError for a bad option).
    """
    bag = os.fspath(path)
    stride = steps if stride is None else int(stride)
    if steps < 1 or stride < 1:
        raise ValueError(f'steps and stride must be >= 1, got {steps}, {stride}')
    check_options(sample_period, match)
    if not os.path.exists(bag):
        raise BagDataError(bag, 'no such file or directory')
    try:
        reader = BagReader(bag)
    except FileNotFoundError:
        raise BagDataError(bag, 'empty bag: no .mcap files')
    except ValueError as error:
        detail = str(error).split(': ', 1)[-1]
        raise BagDataError(bag, f'empty bag: no readable message ({detail})')
    counts, types, messages_digest = scan(bag, reader)
    namespace = loop_topics(bag, types, namespace)
    try:
        loops = read_runs(bag, scale, namespace, sample_period, match)
    except ValueError as error:
        raise BagDataError(bag, str(error).removeprefix(f'{bag}: '))
    # Nothing silently dropped: every state and command recorded is in exactly one run.
    for topic, key, what in ((wire.STATE_TOPIC, 'states', 'states'),
                             (wire.TENSION_TOPIC, 'commands', 'commands')):
        recorded = counts[wire.resolve(topic, namespace)]
        read = sum(loop.counts[key] for loop in loops)
        if read != recorded:
            raise BagDataError(bag, f'read back inconsistently: {read} of {recorded} {what} '
                               'in the runs of the loop')
    loop = loops[0]
    simulator = loop.run_info.get('simulator') or {}
    bag_h = loop.h
    if bag_h is None:
        raise BagDataError(bag, 'sample period unknown: no simulator RunInfo, and the states\' '
                           'header stamps do not give one (give the sample period)')
    # A period read from stamps is measured, one given is rounded: each matches the model's
    # within its tolerance.
    tolerance = PERIOD_TOLERANCES[loop.h_source]
    if h is not None:
        if not math.isclose(bag_h, h, rel_tol=tolerance):
            seconds = loop.scale.tau_to_seconds
            within = '' if loop.h_source == H_FROM_RUN_INFO else f' within {tolerance:.2%}'
            raise BagDataError(bag, f'sample period h = {bag_h:.6g} tau '
                               f'({seconds(bag_h):.6g} s, from {H_SOURCES[loop.h_source]}); '
                               f'the model needs {h:g} tau = {seconds(h):.6g} s{within}')
        bag_h = h
    for each in loops:
        if state_dim is not None and each.x.shape[1] != state_dim:
            raise BagDataError(bag, f'{each.x.shape[1]}-component states; the model needs '
                               f'{state_dim}')

    cuts = [_cut_run(each, steps, stride, simulator.get('max_tension'), max_abs_state,
                     validation_fraction, validation_offset) for each in loops]
    gaps = {key: sum(cut['gaps'][key] for cut in cuts) for key in cuts[0]['gaps']}
    gaps.update(first_step=int(loops[0].step[0]), last_step=int(loops[-1].step[-1]),
                longest_run=max(cut['gaps']['longest_run'] for cut in cuts),
                resets=len(loops) - 1,
                loop_runs=[{'first_step': int(each.step[0]), 'last_step': int(each.step[-1]),
                            'states': int(each.step.size), 'windows': cut['gaps']['windows']}
                           for each, cut in zip(loops, cuts)])
    windows = gaps['windows']
    skipped = {k: gaps[k] for k in ('missing_steps', 'missing_commands', 'held_steps',
                                    'refused_commands', 'non_finite_states',
                                    'out_of_bounds_states', 'conflicting_states') if gaps[k]}
    if not windows:
        what = ', '.join(f'{v} {k.replace("_", " ")}' for k, v in skipped.items())
        states = f'{gaps["states"]} states'
        if len(loops) > 1:
            states += f' in {len(loops)} runs'
        raise BagDataError(bag, f'no complete {steps}-step window: {states}, longest '
                           f'gap-free run {gaps["longest_run"]} steps'
                           + (f' ({what})' if what else ''))

    warnings = []
    read_report = loop.report or reader.report
    for file in read_report.files:
        if file.state != COMPLETE:
            use = '; its recovered windows are used' if file.messages else '; ignored'
            warnings.append(f'{bag}: {file.line()}{use}')
    warnings += _assumptions(bag, loops, bag_h, scale, sample_period)
    if len(loops) > 1:
        warnings.append(f'{bag}: {len(loops)} runs of the loop (the simulator was reset: '
                        f'{", ".join(each.describe() for each in loops)}); windows are cut '
                        'from each')
    if skipped:
        what = ', '.join(f'{v} {k.replace("_", " ")}' for k, v in skipped.items())
        warnings.append(f'{bag}: gaps skipped ({what}); {windows} windows from '
                        f'{gaps["runs"]} gap-free runs')
    if gaps['conflicting_commands']:
        warnings.append(f'{bag}: {gaps["conflicting_commands"]} steps answered by different '
                        'commands: the first (the one a lockstep simulator applies) is used')

    digest, files = content_hash(bag)
    states_by_file = {f.path: (f.state, f.messages) for f in read_report.files}
    for entry in files:
        entry['state'], entry['messages'] = states_by_file.get(entry['file'], ('', 0))
    controller = loop.run_info.get('controller', {})
    excited = sum(int(np.count_nonzero(each.excitation)) for each in loops
                  if each.excitation is not None)
    zone_commands = {'steps': sum(cut['zone']['steps'] for cut in cuts),
                     'sum': float(sum(cut['zone']['sum'] for cut in cuts))}
    provenance = _json({
        'source': 'bag', 'path': os.path.abspath(bag), 'sha256': digest, 'files': files,
        'messages_sha256': messages_digest, 'messages': dict(sorted(counts.items())),
        'namespace': namespace, 'steps': steps,
        'windows': windows, 'h': bag_h, 'h_source': loop.h_source,
        'sample_period_s': loop.scale.tau_to_seconds(bag_h), 'match': loop.match,
        'scale': dataclasses.asdict(loop.scale), 'units': loop.units,
        'plant': simulator, 'controller': controller.get('controller'),
        'model': controller.get('model'), 'excitation': controller.get('excitation'),
        'excited_steps': excited, 'halted': any(each.halted for each in loops),
        'recovered': read_report.recovered, 'gaps': gaps, 'zone_commands': zone_commands,
        'run_info': loop.run_info})

    def joined(key):
        parts = [cut[key] for cut in cuts if len(cut[key][0])]
        if not parts:
            return None
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    data = Dataset(*joined('train'), bag_h, [provenance])
    held = joined('held')
    validation = Dataset(*held, bag_h, [provenance]) if held else None
    return BagWindows(bag, data, provenance, warnings, validation)


def _cut_run(loop, steps, stride, max_tension, max_abs_state, validation_fraction,
             validation_offset):
    """The windows of one run of the loop: {'train': (x, u), 'held': (x, u), 'gaps': counts,
    'zone': the in-zone commands}."""
    step, x, u, raw = loop.step, loop.x, loop.u, loop.tension
    plant_held = loop.held if loop.held is not None else np.zeros(len(step), dtype=bool)
    conflicting = (loop.conflicting if loop.conflicting is not None
                   else np.zeros(len(step), dtype=bool))
    commanded = ~np.isnan(raw)
    with np.errstate(invalid='ignore'):
        accepted = np.isfinite(raw) & (raw >= 0.0)
        if max_tension is not None:
            accepted &= raw <= float(max_tension) * (1.0 + 1e-12)
    finite = np.isfinite(x).all(axis=1)
    with np.errstate(invalid='ignore'):
        state_ok = dynamics.in_domain(x) & np.all(np.abs(x) <= max_abs_state, axis=1)
    trusted = state_ok & ~conflicting       # a step recorded with two states: which is true?
    contiguous = np.diff(step) == 1
    link = contiguous & trusted[:-1] & trusted[1:] & accepted[:-1]
    runs = _runs(link)
    starts = [start + k for start, length in runs for k in range(0, length - steps + 1, stride)]
    held = validation_blocks(runs, steps, validation_fraction, validation_offset)
    starts = [s for s in starts if not any(s < end and s + steps > first for first, end in held)]
    held_starts = [s for first, end in held for s in range(first, end - steps + 1, steps)]

    def cut(where):
        return (np.array([x[s:s + steps + 1] for s in where]).reshape(-1, steps + 1, x.shape[1]),
                np.array([u[s:s + steps] for s in where]).reshape(-1, steps))

    # The commands that held the plant in the 1% zone, each step once: retrain's anchor estimate.
    with np.errstate(invalid='ignore'):
        zone_link = link & in_zone(x[:-1])
    missing = np.diff(step)[~contiguous] - 1
    counts = loop.counts
    gaps = {
        'states': int(len(step)), 'gaps': int(len(missing)),
        'missing_steps': int(missing.sum()),
        'missing_commands': int((~commanded[:-1] & ~plant_held[:-1]).sum()),
        'held_steps': int(plant_held[:-1].sum()),
        'refused_commands': int((commanded[:-1] & ~accepted[:-1]).sum()),
        'non_finite_states': int((~finite).sum()),
        'out_of_bounds_states': int((finite & ~state_ok).sum()),
        'conflicting_states': int(conflicting.sum()),
        'orphan_commands': counts['orphan_commands'],
        'republished_states': counts['republished_states'],
        'repeated_commands': counts['repeated_commands'],
        'conflicting_commands': counts['conflicting_commands'],
        'runs': len(runs), 'longest_run': max((n for _, n in runs), default=0),
        'transitions': int(link.sum()), 'windows': len(starts),
        'validation_windows': len(held_starts),
    }
    return {'train': cut(starts), 'held': cut(held_starts), 'gaps': gaps,
            'zone': {'steps': int(zone_link.sum()), 'sum': float(u[:-1][zone_link].sum())}}


def _assumptions(bag, loops, h, scale, sample_period):
    """Warning lines for what a bag without the simulator's record was read with, for sample
    intervals its stamps do not bear out, and for options its own record overrides."""
    loop, lines = loops[0], []
    if loop.units != UNITS_FROM_RUN_INFO or loop.h_source != H_FROM_RUN_INFO:
        s = loop.scale
        lines.append(f'{bag}: no simulator RunInfo: units {UNITS_SOURCES[loop.units]} (orbit rate '
                     f'{s.orbit_rate:g} rad/s, tether {s.tether_length:g} m, mass {s.mass:g} '
                     f'kg), sample period {s.tau_to_seconds(h):.6g} s = {h:g} tau from '
                     f'{H_SOURCES[loop.h_source]}, commands matched by {loop.match}')
    if loop.h_source != H_FROM_RUN_INFO:
        per_step = np.concatenate([np.diff(each.tau) / np.diff(each.step) for each in loops])
        with np.errstate(invalid='ignore', divide='ignore'):
            off = int(np.sum(~(np.abs(per_step / h - 1.0) <= IRREGULAR_INTERVAL)))
        if off:
            lines.append(f'{bag}: {off} of {per_step.size} sample intervals of the states\' '
                         f'stamps differ from h by more than {IRREGULAR_INTERVAL:.0%}')
    if scale is not None and loop.units == UNITS_FROM_RUN_INFO and scale != loop.scale:
        lines.append(f'{bag}: the units given are not used: the simulator recorded its own')
    if (sample_period is not None and loop.h_source == H_FROM_RUN_INFO
            and not math.isclose(loop.scale.seconds_to_tau(sample_period), h,
                                 rel_tol=GIVEN_PERIOD_TOLERANCE)):
        lines.append(f'{bag}: the sample period given is not used: the simulator recorded its '
                     f'own ({loop.scale.tau_to_seconds(h):.6g} s)')
    return lines


def read_bags(paths, **options):
    """read_windows (same options) for every bag: (list of BagWindows, list of BagDataError).
    Every bad bag is collected, not just the first, so a caller can name them all."""
    good, bad = [], []
    for path in paths:
        try:
            good.append(read_windows(path, **options))
        except BagDataError as error:
            bad.append(error)
    return good, bad


def windows_dataset(bag_windows):
    """The windows of several bags as one Dataset (their h and state size must agree)."""
    return concatenate([b.data for b in bag_windows])
