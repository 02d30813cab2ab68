"""Bags -> training windows: what a good bag gives, and one clear line for each bad one.

Bags are written here without ROS: `BagWriter` with the installed definitions and CDR from the
independent rosbags serializer, laid out as the recorder lays out a lockstep loop (the run
information first, then per step the state, its command and its excitation)."""

import hashlib
import math

import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from tsr_sim import dynamics, wire
from tsr_sim.units import Scale
import yaml

from conftest import ROOT

from tsr_koopman_ctrl import bag
from tsr_koopman_ctrl.bag import definitions
from tsr_koopman_ctrl.bag.checks import find_bags
from tsr_koopman_ctrl.learning import recorded

MSG_DIR = ROOT / 'ros2_ws' / 'src' / 'tsr_msgs' / 'msg'
TSR_TYPES = ('TsrState', 'TensionCommand', 'RunInfo', 'Excitation', 'SimStatus')
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
for _name in TSR_TYPES:
    TYPESTORE.register(get_types_from_msg((MSG_DIR / f'{_name}.msg').read_text(),
                                          f'tsr_msgs/msg/{_name}'))
QOS = [definitions.qos_dict(1, 10, 1, 2, 1, None, None, None)]
#: Not the paper's: the windows must come out in the bag's own units.
SCALE = Scale(orbit_rate=1.0e-3, tether_length=50.0e3, mass=35.0)
H = dynamics.PAPER_STEP


def topic(name, type_name, definition=None, type_hash=None):
    return bag.TopicInfo(name, type_name, definition or definitions.message_definition(type_name),
                         definitions.type_hash(type_name) if type_hash is None else type_hash,
                         QOS)


def _cdr(type_name, **fields):
    return bytes(TYPESTORE.serialize_cdr(TYPESTORE.types[type_name](**fields), type_name))


def _header(seconds):
    time = TYPESTORE.types['builtin_interfaces/msg/Time']
    sec = math.floor(seconds)
    return TYPESTORE.types['std_msgs/msg/Header'](
        stamp=time(sec=sec, nanosec=int(round((seconds - sec) * 1e9)) % 10 ** 9), frame_id='')


def state_cdr(x, step, scale=SCALE, run=0, seconds=None):
    """A TsrState of run `run`, stamped `seconds` (default the step's sim time)."""
    si = scale.state_to_si(np.asarray(x, dtype=float))
    seconds = scale.tau_to_seconds(step * H) if seconds is None else seconds
    return _cdr('tsr_msgs/msg/TsrState', header=_header(seconds),
                step=int(step), run=int(run), theta=si[0], theta_rate=si[1], length=si[2],
                length_rate=si[3], has_out_of_plane=False, beta=0.0, beta_rate=0.0)


def tension_cdr(u, step, scale=SCALE, type_name='tsr_msgs/msg/TensionCommand', hold=False):
    hold = {'hold': hold} if type_name.endswith('TensionCommand') else {}
    return _cdr(type_name, header=_header(0.0), step=int(step),
                tension=float(scale.u_to_tension(u)), **hold)


def run_info_cdr(role, configuration):
    return _cdr('tsr_msgs/msg/RunInfo', header=_header(0.0), node=f'/{role}', role=role,
                configuration=yaml.safe_dump(configuration, sort_keys=False))


def simulator_info(scale=SCALE, **changes):
    return {'mode': 'lockstep', 'step': H, 'substeps': 10, 'initial_state': [0, 0, -0.99, 0.5],
            'scale': {'orbit_rate': scale.orbit_rate, 'tether_length': scale.tether_length,
                      'mass': scale.mass},
            'max_tension': scale.u_to_tension(dynamics.TENSION_LIMIT), 'max_steps': 0,
            'process_noise_std': [], 'sensor_noise_std': [], 'seed': 0, **changes}


def controller_info(scale=SCALE):
    return {'controller': 'linear_lqr', 'settings': {'r': 1.0},
            'scale': {'orbit_rate': scale.orbit_rate, 'tether_length': scale.tether_length,
                      'mass': scale.mass},
            'excitation': {'kind': 'prbs', 'amplitude': 0.3, 'hold': 5, 'seed': 0}}


def loop_data(n, seed=0):
    """n states and the applied tensions (law + excitation) of a made-up, plausible loop."""
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n),
                         rng.uniform(-0.9, 0.1, n), rng.uniform(-0.5, 0.5, n)])
    law = rng.uniform(1.0, 4.0, n)
    excitation = np.where((np.arange(n) // 5) % 2 == 0, 0.3, -0.3)
    return x, law + excitation, excitation


def write_loop(directory, x, u, steps=None, excitation=None, simulator=None, scale=SCALE,
               run_info=True, state_definition=None, after=(), chunk_size=1 << 20,
               state_hash=None, runs=()):
    """A lockstep loop as the recorder stores it; u[i] NaN: no command for state i. `after`:
    extra (topic, cdr) messages at the end (republished states, stray commands). `runs`: more
    (x, u, steps) runs recorded after it, as a simulator reset between them leaves them (run
    numbers 1, 2, ...).
    `state_definition`, `state_hash`: what the state topic is recorded with (default: the
    installed definition and hash; '' hash: none)."""
    steps = np.arange(len(x)) if steps is None else np.asarray(steps)
    with bag.BagWriter(str(directory), chunk_size=chunk_size) as writer:
        writer.add_topic(topic('/tsr/run_info', 'tsr_msgs/msg/RunInfo'))
        writer.add_topic(topic('/tsr/state', 'tsr_msgs/msg/TsrState', state_definition,
                               state_hash))
        writer.add_topic(topic('/tsr/tension_cmd', 'tsr_msgs/msg/TensionCommand'))
        writer.add_topic(topic('/tsr/excitation', 'tsr_msgs/msg/Excitation'))
        time = [0]

        def write(name, data):
            time[0] += 1000
            writer.write(name, data, log_time_ns=time[0])

        if run_info:
            write('/tsr/run_info', run_info_cdr('simulator', simulator or simulator_info(scale)))
            write('/tsr/run_info', run_info_cdr('controller', controller_info(scale)))
        for run, (run_x, run_u, run_steps) in enumerate([(x, u, steps)] + list(runs)):
            for i, step in enumerate(np.arange(len(run_x)) if run_steps is None else run_steps):
                write('/tsr/state', state_cdr(run_x[i], step, scale, run))
                if not np.isnan(run_u[i]):
                    write('/tsr/tension_cmd', tension_cdr(run_u[i], step, scale))
                    if excitation is not None:
                        write('/tsr/excitation', tension_cdr(excitation[i], step, scale,
                                                             'tsr_msgs/msg/Excitation'))
        for name, data in after:
            write(name, data)
    return directory


@pytest.fixture(scope='module')
def good_bag(tmp_path_factory):
    x, u, excitation = loop_data(95)
    path = write_loop(tmp_path_factory.mktemp('bags') / 'good', x, u, excitation=excitation)
    return path, x, u, excitation


# --------------------------------------------------------------------------- a good bag

def test_windows_of_a_good_bag_are_the_states_and_applied_tensions_written(good_bag):
    path, x, u, excitation = good_bag
    windows = recorded.read_windows(path, steps=30, h=H, state_dim=4)
    data = windows.data
    assert len(data) == 3 and data.steps == 30 and data.h == H      # 95 states: 3 windows
    for k in range(3):
        np.testing.assert_allclose(data.x[k], x[30 * k:30 * k + 31], rtol=0, atol=1e-12)
        # The applied command (law + excitation), in the bag's own units, not the paper's.
        np.testing.assert_allclose(data.u[k], u[30 * k:30 * k + 30], rtol=0, atol=1e-12)
    assert not np.allclose(data.u[0], (u - excitation)[:30])
    paper = Scale().tension_to_u(SCALE.u_to_tension(u[:30]))
    assert not np.allclose(data.u[0], paper)
    assert windows.warnings == []
    prov = windows.provenance
    files = sorted(path.glob('*.mcap'))
    assert prov['sha256'] == hashlib.sha256(b''.join(f.read_bytes() for f in files)).hexdigest()
    assert prov['files'][0]['sha256'] == hashlib.sha256(files[0].read_bytes()).hexdigest()
    assert prov['messages'] == {'/tsr/excitation': 95, '/tsr/run_info': 2,
                                '/tsr/state': 95, '/tsr/tension_cmd': 95}
    assert prov['windows'] == 3 and prov['scale'] == {'orbit_rate': 1.0e-3,
                                                      'tether_length': 50.0e3, 'mass': 35.0}
    assert prov['controller'] == 'linear_lqr' and prov['plant']['mode'] == 'lockstep'
    assert prov['excitation']['kind'] == 'prbs' and prov['excited_steps'] == 95
    assert prov['gaps']['missing_steps'] == 0 and prov['gaps']['transitions'] == 94
    assert data.provenance == [prov]


def test_republished_identical_states_are_fine(tmp_path):
    x, u, _ = loop_data(40)
    path = write_loop(tmp_path / 'b', x, u, after=[('/tsr/state', state_cdr(x[10], 10))])
    windows = recorded.read_windows(path, steps=30)
    assert len(windows.data) == 1 and windows.provenance['gaps']['republished_states'] == 1


def test_the_controller_s_safe_tension_answers_no_step_and_changes_nothing(tmp_path):
    """Safe tensions (step NO_STEP) pair with no state: the windows and the loop read back
    are the commands that answered states, with no warning. Stamped with a state's step, as
    an older controller did, one is a second, different command for that step."""
    x, u, _ = loop_data(40)
    safe = dynamics.EQUILIBRIUM_TENSION
    path = write_loop(tmp_path / 'b', x, u,
                      after=[('/tsr/tension_cmd', tension_cdr(safe, wire.NO_STEP))] * 2)
    windows = recorded.read_windows(path, steps=30, h=H, state_dim=4)
    np.testing.assert_allclose(windows.data.u[0], u[:30], rtol=0, atol=1e-12)
    assert windows.warnings == []
    np.testing.assert_allclose(bag.read_loop(path).u, u, rtol=0, atol=1e-12)
    stamped = write_loop(tmp_path / 'old', x, u,
                         after=[('/tsr/tension_cmd', tension_cdr(safe, 39))])
    assert any('1 steps answered by different commands' in warning
               for warning in recorded.read_windows(stamped, steps=30).warnings)


def test_gaps_are_skipped_and_counted(tmp_path):
    x, u, _ = loop_data(140, seed=1)
    u[75] = np.nan                                     # state 75 has no command
    u[100] = -1.0                                      # a command the simulator refuses
    x[120, 1] = np.nan                                 # a non-finite state
    steps = np.r_[np.arange(0, 40), np.arange(45, 145)]   # steps 40..44 missing
    windows = recorded.read_windows(write_loop(tmp_path / 'b', x, u, steps=steps), steps=10)
    gaps = windows.provenance['gaps']
    assert (gaps['missing_steps'], gaps['gaps'], gaps['missing_commands'],
            gaps['refused_commands'], gaps['non_finite_states']) == (5, 1, 1, 1, 1)
    # Gap-free runs (state indices): 0-39 (39 transitions), 40-75, 76-100, 101-119, 121-139.
    assert gaps['runs'] == 5 and len(windows.data) == 3 + 3 + 2 + 1 + 1
    np.testing.assert_allclose(windows.data.x[3], x[40:51], atol=1e-12)   # a run's start
    np.testing.assert_allclose(windows.data.u[3], u[40:50], atol=1e-12)
    for window in windows.data.u:
        assert np.all(window >= 0)
    assert len(windows.warnings) == 1
    assert ('5 missing steps, 1 missing commands, 1 refused commands, 1 non finite states'
            in windows.warnings[0])


def test_overlapping_windows_start_every_stride_steps_and_never_span_a_gap(tmp_path):
    x, u, _ = loop_data(140, seed=1)
    steps = np.r_[np.arange(0, 40), np.arange(45, 145)]   # steps 40..44 missing
    windows = recorded.read_windows(write_loop(tmp_path / 'b', x, u, steps=steps), steps=10,
                                    stride=4)
    # Runs: states 0-39 (39 transitions) and 40-139 (99): starts 0, 4, .., 28 and 40, .., 128.
    starts = list(range(0, 39 - 10 + 1, 4)) + list(range(40, 139 - 10 + 1, 4))
    assert len(windows.data) == windows.provenance['windows'] == len(starts) == 8 + 23
    for window, start in zip(windows.data.x, starts):
        np.testing.assert_allclose(window, x[start:start + 11], atol=1e-12)
    for window, start in zip(windows.data.u, starts):
        np.testing.assert_allclose(window, u[start:start + 10], atol=1e-12)
    with pytest.raises(ValueError, match='stride'):
        recorded.read_windows(tmp_path / 'b', steps=10, stride=0)


def test_validation_blocks_share_no_step_with_training_windows(tmp_path):
    x, u, _ = loop_data(700, seed=2)
    x[400:, (0, 2)] = 0.005                             # the last 300 states in the 1% zone
    path = write_loop(tmp_path / 'b', x, u)
    windows = recorded.read_windows(path, steps=10, stride=2, validation_fraction=0.25,
                                    validation_offset=1)
    # One run of 699 transitions; blocks of 30 steps; every 4th block from block 1: blocks
    # 1, 5, 9, 13, 17, 21 -> steps [30, 60), [150, 180), ...; 3 windows each.
    blocks = [(30 * j, 30 * j + 30) for j in range(1, 699 // 30, 4)]
    assert recorded.validation_blocks([(0, 699)], 10, 0.25, 1) == blocks
    held = windows.validation
    assert len(held) == windows.provenance['gaps']['validation_windows'] == 3 * len(blocks)
    starts = [s for first, end in blocks for s in range(first, end - 9, 10)]
    for window, start in zip(held.x, starts):
        np.testing.assert_allclose(window, x[start:start + 11], atol=1e-12)
    train_starts = [s for s in range(0, 699 - 10 + 1, 2)
                    if not any(s < end and s + 10 > first for first, end in blocks)]
    assert len(windows.data) == len(train_starts)
    for window, start in zip(windows.data.x, train_starts):
        np.testing.assert_allclose(window, x[start:start + 11], atol=1e-12)
    # The in-zone commands, each step once (the anchor estimate): transitions 400..698.
    zone = windows.provenance['zone_commands']
    assert zone['steps'] == 299 and zone['sum'] == pytest.approx(u[400:699].sum(), rel=1e-12)


def test_truncated_bag_is_recovered_with_a_warning(tmp_path):
    x, u, excitation = loop_data(600, seed=2)
    path = write_loop(tmp_path / 'b', x, u, excitation=excitation, chunk_size=4000)
    full = recorded.read_windows(path, steps=30)
    mcap = path / 'b_0.mcap'
    mcap.write_bytes(mcap.read_bytes()[:mcap.stat().st_size // 2])   # what a kill leaves
    windows = recorded.read_windows(path, steps=30)
    assert 0 < len(windows.data) < len(full.data)
    np.testing.assert_array_equal(windows.data.x, full.data.x[:len(windows.data)])
    assert len(windows.warnings) == 1
    assert windows.warnings[0].startswith(f'{path}: b_0.mcap: truncated: ')
    assert 'messages recovered' in windows.warnings[0]
    assert windows.provenance['recovered'] and windows.provenance['files'][0]['state'] == \
        'truncated'


def test_the_messages_hash_is_the_recorded_messages_not_the_files(good_bag, tmp_path):
    """Identity for retrain's "trained on and held out" check: another chunking of the same
    messages (what `bag recover` writes) is the same data; one other tension is not."""
    path, x, u, excitation = good_bag
    rechunked = write_loop(tmp_path / 'rechunked', x, u, excitation=excitation, chunk_size=2000)
    changed = u.copy()
    changed[50] += 0.125
    other = write_loop(tmp_path / 'other', x, changed, excitation=excitation)
    first, again, different = (recorded.read_windows(b, steps=30).provenance
                               for b in (path, rechunked, other))
    assert first['sha256'] != again['sha256']                  # other bytes in the files
    assert first['messages_sha256'] == again['messages_sha256']
    assert first['messages_sha256'] != different['messages_sha256']
    assert first['messages_sha256'] not in (first['sha256'], different['sha256'])


# --------------------------------------------------------------------------- runs

def write_messages(directory, messages):
    """The simulator's RunInfo, then (topic, cdr) `messages`, into a loop bag, 1 us apart."""
    messages = [('/tsr/run_info', run_info_cdr('simulator', simulator_info()))] + messages
    with bag.BagWriter(str(directory)) as writer:
        for name, type_name in (('/tsr/run_info', 'tsr_msgs/msg/RunInfo'),
                                ('/tsr/state', 'tsr_msgs/msg/TsrState'),
                                ('/tsr/tension_cmd', 'tsr_msgs/msg/TensionCommand'),
                                ('/tsr/sim_status', 'tsr_msgs/msg/SimStatus')):
            writer.add_topic(topic(name, type_name))
        for i, (name, data) in enumerate(messages):
            writer.write(name, data, log_time_ns=1000 * (i + 1))
    return directory


def lockstep(x, u, run=0):
    return [m for i in range(len(x)) for m in (('/tsr/state', state_cdr(x[i], i, run=run)),
                                               ('/tsr/tension_cmd', tension_cdr(u[i], i)))]


def test_each_run_of_a_reset_bag_reads_back_as_written(tmp_path):
    x, u, _ = loop_data(40)
    x2, u2, _ = loop_data(35, seed=7)
    path = write_messages(tmp_path / 'b', lockstep(x, u) + lockstep(x2, u2, run=1))
    runs = bag.read_runs(path)
    assert [(loop.run, loop.runs) for loop in runs] == [(0, 2), (1, 2)]
    for loop, (xs, us) in zip(runs, ((x, u), (x2, u2))):
        np.testing.assert_array_equal(loop.step, np.arange(len(xs)))
        np.testing.assert_allclose(loop.x, xs, rtol=0, atol=1e-12)
        np.testing.assert_allclose(loop.u, us, rtol=0, atol=1e-12)
        np.testing.assert_allclose(loop.tau, np.arange(len(xs)) * H, rtol=0, atol=1e-9)
        assert loop.counts == {'states': len(xs), 'commands': len(xs), 'republished_states': 0,
                               'repeated_commands': 0, 'conflicting_commands': 0,
                               'orphan_commands': 0, 'conflicting_states': 0}
    np.testing.assert_array_equal(bag.read_loop(path, run=1).x, runs[1].x)
    with pytest.raises(ValueError, match=r'has no run 2: run 0: steps 0-39 \(40 states\), '):
        bag.read_loop(path, run=2)


def test_no_command_of_one_run_is_matched_to_a_state_of_the_other(tmp_path):
    """Late answers to run 0 recorded after the reset (to its last state, and to a step run 1
    reaches later) stay in run 0; run 1's steps get run 1's commands."""
    x, u, _ = loop_data(40)
    x2, u2, _ = loop_data(35, seed=7)
    run1 = lockstep(x2, u2, run=1)
    messages = (lockstep(x, u)[:-1] + run1[:1]                      # reset before command 39
                + [('/tsr/tension_cmd', tension_cdr(u[39], 39)),     # run 0's late answer
                   ('/tsr/tension_cmd', tension_cdr(9.0, 5))]        # a stray late one
                + run1[1:])
    first, second = bag.read_runs(write_messages(tmp_path / 'b', messages))
    np.testing.assert_allclose(first.u, u, rtol=0, atol=1e-12)
    np.testing.assert_allclose(second.u, u2, rtol=0, atol=1e-12)
    assert first.counts['conflicting_commands'] == 1 and second.counts['commands'] == 35


def test_a_halted_run_stays_halted_after_the_reset_s_status(tmp_path):
    """The reset publishes the new run's status (step 0) before its first state: it carries
    run 1's number and is run 1's; run 0 keeps the halt it ended with."""
    x, u, _ = loop_data(40)
    x2, u2, _ = loop_data(30, seed=7)

    def status(code, step, run):
        return ('/tsr/sim_status', _cdr('tsr_msgs/msg/SimStatus', header=_header(0.0),
                                        status=code, message='', step=step, run=run,
                                        holding=False, commands_accepted=0, rejected_non_finite=0,
                                        rejected_negative=0, rejected_over_limit=0,
                                        rejected_stale=0, command_timeouts=0))
    first, second = bag.read_runs(write_messages(
        tmp_path / 'b', lockstep(x, u) + [status(1, 40, 0), status(0, 0, 1)]
        + lockstep(x2, u2, run=1)))
    assert first.halted and first.sim_status.step == 40
    assert not second.halted and second.sim_status.step == 0


def test_a_reset_to_the_same_start_is_a_run_of_its_own_from_its_first_state(tmp_path):
    """Run 1 starts with run 0's first five states and commands: the run number tells them
    apart, not the values, so none is taken for a republished state of run 0."""
    x, u, _ = loop_data(40)
    x2, u2, _ = loop_data(30, seed=7)
    x2[:5], u2[:5] = x[:5], u[:5]
    first, second = bag.read_runs(write_messages(tmp_path / 'b', lockstep(x, u)
                                                 + lockstep(x2, u2, run=1)))
    assert first.counts['republished_states'] == 0 and first.step.size == 40
    np.testing.assert_allclose(second.x, x2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(second.u, u2, rtol=0, atol=1e-12)
    assert second.counts['repeated_commands'] == 0 and second.counts['commands'] == 30


def test_runs_split_at_the_run_number_whatever_the_log_times(tmp_path):
    """On sim time a reset sends the recorder's clock back to 0, and two simulators on one
    domain mix their clocks in its log times: the runs come from the run numbers and the
    recorded order, so log times that jump back and forth change nothing."""
    x, u, _ = loop_data(40)
    x2, u2, _ = loop_data(35, seed=7)
    messages = ([('/tsr/run_info', run_info_cdr('simulator', simulator_info()))]
                + lockstep(x, u) + lockstep(x2, u2, run=1))
    rng = np.random.default_rng(0)
    with bag.BagWriter(str(tmp_path / 'b')) as writer:
        for name, type_name in (('/tsr/run_info', 'tsr_msgs/msg/RunInfo'),
                                ('/tsr/state', 'tsr_msgs/msg/TsrState'),
                                ('/tsr/tension_cmd', 'tsr_msgs/msg/TensionCommand')):
            writer.add_topic(topic(name, type_name))
        for name, data in messages:
            writer.write(name, data, log_time_ns=int(rng.integers(1, 10 ** 9)))
    first, second = bag.read_runs(tmp_path / 'b')
    for loop, (xs, us) in zip((first, second), ((x, u), (x2, u2))):
        np.testing.assert_allclose(loop.x, xs, rtol=0, atol=1e-12)
        np.testing.assert_allclose(loop.u, us, rtol=0, atol=1e-12)
    assert (first.sim_run, second.sim_run) == (0, 1)


def test_a_bag_recorded_before_states_carried_their_run_number_is_refused(tmp_path):
    """TsrState without `run` (the definition before it): refused in one line, by the loop
    reader (it cannot be split into runs) and by the definition check before training."""
    text = (MSG_DIR / 'TsrState.msg').read_text()
    old_text = '\n'.join(line for line in text.splitlines()
                         if not line.startswith('uint32 run'))
    assert old_text != text
    old = get_typestore(Stores.ROS2_JAZZY)
    old.register(get_types_from_msg(old_text, 'tsr_msgs/msg/TsrState'))
    x, u, _ = loop_data(40)
    sep = '=' * 80
    header, time = (open(definitions._interface_file(t, '.msg')).read()
                    for t in ('std_msgs/msg/Header', 'builtin_interfaces/msg/Time'))
    definition = (f'{old_text}\n{sep}\nMSG: builtin_interfaces/Time\n{time}\n{sep}\n'
                  f'MSG: std_msgs/Header\n{header}')
    with bag.BagWriter(str(tmp_path / 'b')) as writer:
        writer.add_topic(topic('/tsr/state', 'tsr_msgs/msg/TsrState', definition, ''))
        writer.add_topic(topic('/tsr/tension_cmd', 'tsr_msgs/msg/TensionCommand'))
        for i in range(len(x)):
            si = SCALE.state_to_si(x[i])
            state = old.types['tsr_msgs/msg/TsrState'](
                header=old.types['std_msgs/msg/Header'](
                    stamp=old.types['builtin_interfaces/msg/Time'](sec=i, nanosec=0),
                    frame_id=''), step=i, theta=si[0], theta_rate=si[1], length=si[2],
                length_rate=si[3], has_out_of_plane=False, beta=0.0, beta_rate=0.0)
            writer.write('/tsr/state', bytes(old.serialize_cdr(state, 'tsr_msgs/msg/TsrState')),
                         2 * i + 1)
            writer.write('/tsr/tension_cmd', tension_cdr(u[i], i), 2 * i + 2)
    with pytest.raises(ValueError) as caught:
        bag.read_runs(tmp_path / 'b')
    assert str(caught.value) == (f'{tmp_path / "b"}: its TsrState messages carry no run number '
                                 '(recorded under an older TsrState definition): it cannot be '
                                 'split into runs')
    bad(tmp_path / 'b', "TsrState was recorded with another message definition than the "
        r"installed one \(tsr_msgs/TsrState declaration 3: 'float64 theta' in the bag, "
        r"'uint32 run' installed\)")


def test_a_bag_starting_at_a_later_run_numbers_its_runs_from_0(tmp_path):
    """A recorder started after two resets: the bag's runs are 0 and 1, the simulator's 2 and
    3 (`sim_run`, and in the description)."""
    x, u, _ = loop_data(40)
    x2, u2, _ = loop_data(35, seed=7)
    path = write_messages(tmp_path / 'b', lockstep(x, u, run=2) + lockstep(x2, u2, run=3))
    first, second = bag.read_runs(path)
    assert [(r.run, r.sim_run) for r in (first, second)] == [(0, 2), (1, 3)]
    assert second.describe() == 'run 1 (simulator run 3): steps 0-34 (35 states)'


# --------------------------------------------------------------------------- bad bags

def bad(path, match, **options):
    with pytest.raises(recorded.BagDataError, match=match) as caught:
        recorded.read_windows(path, **options)
    message = str(caught.value)
    assert message.startswith(f'{path}: ') and '\n' not in message
    return message


def test_an_empty_bag(tmp_path):
    (tmp_path / 'b').mkdir()
    (tmp_path / 'b' / 'b_0.mcap').write_bytes(b'')
    bad(tmp_path / 'b', 'empty bag: no readable message')
    (tmp_path / 'c').mkdir()
    (tmp_path / 'c' / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    bad(tmp_path / 'c', 'empty bag: no .mcap files')


def test_a_bag_of_other_types(tmp_path):
    type_name = 'std_msgs/msg/String'
    with bag.BagWriter(str(tmp_path / 'b')) as writer:
        writer.add_topic(topic('/tsr/state', type_name))
        writer.add_topic(topic('/tsr/tension_cmd', 'tsr_msgs/msg/TensionCommand'))
        writer.write('/tsr/state', _cdr(type_name, data='hello'), 1)
        writer.write('/tsr/tension_cmd', tension_cdr(3.0, 0), 2)
    bad(tmp_path / 'b', r'wrong types: no tsr_msgs/msg/TsrState messages \(topics: /tsr/state '
        r'\[std_msgs/msg/String\]')
    x, u, _ = loop_data(40)
    u[:] = np.nan
    bad(write_loop(tmp_path / 'c', x, u), 'wrong types: no tsr_msgs/msg/TensionCommand')


def test_another_message_definition(tmp_path):
    """Another field type, name or order is refused: by the type hash when the bag has one, by
    the normalised definition when it has none."""
    x, u, _ = loop_data(40)
    installed = definitions.message_definition('tsr_msgs/msg/TsrState')
    changed = installed.replace('float64 length ', 'float32 length ')
    assert changed != installed
    message = bad(write_loop(tmp_path / 'b', x, u, state_definition=changed, state_hash=''),
                  'TsrState was recorded with another message definition')
    assert ("tsr_msgs/TsrState declaration 6: 'float32 length' in the bag, 'float64 length' "
            'installed') in message
    swapped = installed.replace('float64 beta ', 'float64 tmp ').replace(
        'float64 beta_rate', 'float64 beta').replace('float64 tmp ', 'float64 beta_rate ')
    bad(write_loop(tmp_path / 'c', x, u, state_definition=swapped, state_hash=''),
        "declaration 9: 'float64 beta_rate' in the bag, 'float64 beta' installed")
    other_hash = 'RIHS01_' + '0' * 64
    message = bad(write_loop(tmp_path / 'd', x, u, state_hash=other_hash),
                  f'type hash {other_hash} in the bag, RIHS01_')


def test_the_same_type_spelled_otherwise_is_accepted(tmp_path):
    """Same hash, or no hash and the same normalised definition: other spellings of the same
    type (the project's earlier 'MSG: pkg/msg/Type' without blank lines, dependencies in field
    order; other comments and whitespace) give the same windows. Comments are ignored though
    ours carry units: the type hash ignores them too, and units are REP 103 SI by convention."""
    x, u, _ = loop_data(40)
    sep = '=' * 80
    read = definitions._interface_file
    header, time = (open(read(t, '.msg')).read()
                    for t in ('std_msgs/msg/Header', 'builtin_interfaces/msg/Time'))
    installed = definitions.message_definition('tsr_msgs/msg/TsrState')
    state = open(read('tsr_msgs/msg/TsrState', '.msg')).read()
    old_spelling = (f'{state.rstrip()}\n{sep}\nMSG: std_msgs/msg/Header\n{header.rstrip()}\n'
                    f'{sep}\nMSG: builtin_interfaces/msg/Time\n{time}')
    commented = installed.replace('[m]', '[km]').replace('float64 theta ', 'float64   theta ')
    expected = recorded.read_windows(write_loop(tmp_path / 'a', x, u), steps=30).data.x
    for name, text, type_hash in (('old', old_spelling, ''), ('comments', commented, ''),
                                  ('hash', commented, None)):
        windows = recorded.read_windows(write_loop(tmp_path / name, x, u, state_definition=text,
                                                   state_hash=type_hash), steps=30)
        np.testing.assert_array_equal(windows.data.x, expected)


def test_a_reset_splits_the_bag_into_runs_and_windows_come_from_each(tmp_path):
    """A reset restarts the step count: the runs are cut apart, each command stays with its
    own run's state (a late answer to run 0 recorded after the reset included), and both runs
    give windows."""
    x, u, _ = loop_data(40)
    x2, u2, _ = loop_data(35, seed=7)
    path = write_loop(tmp_path / 'b', x, u, runs=[(x2, u2, None)])
    with pytest.raises(ValueError) as caught:
        bag.read_loop(path)
    assert str(caught.value) == (
        f'{path} holds 2 runs of the loop (the simulator was reset): run 0: steps 0-39 (40 '
        'states), run 1: steps 0-34 (35 states); read one with read_loop(path, run=k), k in '
        '0..1, or all with read_runs(path)')
    windows = recorded.read_windows(path, steps=10)
    assert len(windows.data) == 3 + 3
    np.testing.assert_allclose(windows.data.x[3], x2[:11], atol=1e-12)
    np.testing.assert_allclose(windows.data.u[3], u2[:10], atol=1e-12)
    assert windows.provenance['gaps']['resets'] == 1
    assert [r['states'] for r in windows.provenance['gaps']['loop_runs']] == [40, 35]
    assert f'{path}: 2 runs of the loop (the simulator was reset: ' in windows.warnings[0]


def test_a_step_recorded_with_two_states_is_kept_out_of_the_windows(tmp_path):
    """A state of the run's number and a step it has, with other values (a second publisher):
    not a reset, but a step whose true state is unknown. The first is kept in the loop, the
    step is flagged and counted, and no window uses it."""
    x, u, _ = loop_data(70)
    other = x[35] + 0.01
    path = write_loop(tmp_path / 'b', x, u, after=[('/tsr/state', state_cdr(other, 35))])
    windows = recorded.read_windows(path, steps=30)
    # Gap-free runs: transitions 0..34 and 36..69, one 30-step window each.
    assert len(windows.data) == 2
    np.testing.assert_allclose(windows.data.x[0], x[:31], atol=1e-12)
    np.testing.assert_allclose(windows.data.x[1], x[36:67], atol=1e-12)
    gaps = windows.provenance['gaps']
    assert gaps['conflicting_states'] == 1 and gaps['resets'] == 0
    assert '1 conflicting states' in windows.warnings[0]
    loop = bag.read_loop(path)
    np.testing.assert_allclose(loop.x[35], x[35], atol=1e-12)
    assert loop.conflicting.tolist() == [s == 35 for s in range(70)]
    assert loop.counts['conflicting_states'] == 1 and loop.counts['states'] == 71


def test_no_complete_window(tmp_path):
    x, u, _ = loop_data(60)
    u[29] = np.nan                                     # runs of 29 transitions each side
    bad(write_loop(tmp_path / 'b', x, u), r'no complete 30-step window: 60 states, longest '
        r'gap-free run 29 steps \(1 missing commands\)')


def test_the_sample_period_and_state_size_must_match(tmp_path):
    x, u, _ = loop_data(40)
    message = bad(write_loop(tmp_path / 'c', x, u, simulator=simulator_info(step=0.02)),
                  'h = 0.02 tau', h=H)
    assert "from the simulator's RunInfo); the model needs 0.01 tau" in message
    bad(write_loop(tmp_path / 'd', x, u), '4-component states; the model needs 6',
        state_dim=6)


def test_find_bags_walks_directories_and_reads_each_bag_once(good_bag, tmp_path):
    path = good_bag[0]
    x, u, _ = loop_data(40)
    nested = write_loop(tmp_path / 'runs' / 'day1' / 'b1', x, u)
    write_loop(tmp_path / 'runs' / 'b0', x, u)
    assert find_bags([tmp_path / 'runs', nested, path]) == [
        str(tmp_path / 'runs' / 'b0'), str(nested), str(path)]
    (tmp_path / 'empty_dir').mkdir()
    with pytest.raises(recorded.BagDataError, match='no bag below it'):
        find_bags([tmp_path / 'empty_dir'])
    good, errors = recorded.read_bags([path, tmp_path / 'missing'], steps=30)
    assert len(good) == 1 and len(errors) == 1
    assert str(errors[0]) == f'{tmp_path / "missing"}: no such file or directory'


def test_a_bag_without_commands_reads_back_with_one_warning_line(tmp_path):
    """States alone (a recorder started without a controller): the loop reads back, its
    tensions NaN, and a warning line says why."""
    x, _, _ = loop_data(40)
    path = write_loop(tmp_path / 'b', x, np.full(40, np.nan))
    with pytest.warns(bag.BagWarning) as caught:
        loop = bag.read_loop(path)
    assert [str(w.message) for w in caught] == [
        f'{path}: no tsr_msgs/msg/TensionCommand on /tsr/tension_cmd: every tension u is NaN']
    assert np.isnan(loop.u).all() and loop.step.size == 40


def test_a_sample_period_given_as_printed_is_the_model_s_and_another_is_refused(
        tmp_path, capsys):
    """A bag without RunInfo in the paper's units: 0.01 tau is 8.471704... s. The period as
    `bag runs` prints it (8.4717) and as the help rounds it (8.472) are the model's; 8.47 is
    not, and the refusal gives the digits to tell."""
    from tsr_koopman_ctrl.commands import bag as bag_tool
    x, u, _ = loop_data(40)
    path = write_loop(tmp_path / 'b', x, u, scale=Scale(), run_info=False)
    assert bag_tool.main(['runs', str(path)]) == 0
    (sample,) = [line for line in capsys.readouterr().out.splitlines()
                 if line.startswith('sample:')]
    printed = sample.split(' = ')[2].split(' s ')[0]
    assert printed == '8.4717'
    for period in (printed, '8.472', Scale().tau_to_seconds(H)):
        windows = recorded.read_windows(path, steps=30, h=H, sample_period=float(period))
        assert windows.data.h == H and len(windows.data) == 1
    message = bad(path, 'sample period', h=H, sample_period=8.47)
    assert message == (f'{path}: sample period h = 0.00999799 tau (8.47 s, from the option '
                       'given); the model needs 0.01 tau = 8.4717 s within 0.01%')
    from tsr_koopman_ctrl.commands import retrain
    assert "within a relative 0.0001: the paper's 0.01 tau is 8.4717 s" in ' '.join(
        retrain.parser().format_help().split())
