"""Bags as hardware writes them: only tsr/state and tsr/tension_cmd, no RunInfo, no statuses,
commands tied to no step. Written here by the `rosbags` library (not the project's writer) with
the installed message definitions; read by `bag runs`, `read_windows` and `retrain`.

And commands matched by time (zero-order hold) where the simulator's record says timed: a hold,
a plant holding on its own, a reset that starts a run without a tension in force."""

import json
import math
import pathlib
import sys

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_types_from_msg, get_typestore, Stores
from tsr_sim import dynamics, wire
from tsr_sim.units import Scale

from tsr_koopman_ctrl import bag
from tsr_koopman_ctrl.commands import bag as bag_tool
from tsr_koopman_ctrl.commands import retrain
from tsr_koopman_ctrl.learning import recorded

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from test_recorded import (_cdr, _header, run_info_cdr, simulator_info,  # noqa: E402
                           state_cdr, tension_cdr, topic)

#: The hardware's units: not the paper's, so the options must be what converts them.
SCALE = Scale(orbit_rate=1.0e-3, tether_length=50.0e3, mass=35.0)
H = dynamics.PAPER_STEP
PERIOD = SCALE.tau_to_seconds(H)          # 10 s a sample
EPOCH = 1.7e9                             # the hardware's clock: seconds since 1970
UNITS = ['--orbit-rate', '1e-3', '--tether-length', '5e4', '--mass', '35']
TINY = {'lift_dim': 4, 'hidden': 16, 'layers': 2, 'input_hidden': 8, 'input_layers': 1,
        'input_terms': 3, 'batch_size': 32, 'learning_rate': 3e-3, 'epochs': 1}


def installed_typestore():
    """A Jazzy typestore with tsr_msgs registered from the installed .msg files."""
    from ament_index_python.packages import get_package_share_directory
    store = get_typestore(Stores.ROS2_JAZZY)
    share = pathlib.Path(get_package_share_directory('tsr_msgs'))
    for name in ('TsrState', 'TensionCommand'):
        store.register(get_types_from_msg((share / 'msg' / f'{name}.msg').read_text(),
                                          f'tsr_msgs/msg/{name}'))
    return store


def hardware_loop(n, seed=0):
    """A plant under a zero-order hold of commands that carry no step: per sample the commands
    received in it (none: the previous holds; two: the later one), as seconds after the
    sample's state and tensions [N]. Returns (x, applied u per sample, commands), where
    commands are (seconds, tension) and applied[k] the tension in force over sample k (NaN
    for sample 0: the plant runs on its own until the first command, which is sent before
    the first state and so is not in force)."""
    rng = np.random.default_rng(seed)
    commands = [(EPOCH - 0.5, SCALE.u_to_tension(3.0))]     # before the first state
    applied = np.full(n - 1, np.nan)
    in_force = math.nan
    for k in range(1, n - 1):
        count = 0 if k % 7 == 0 else (2 if k % 5 == 0 else 1)
        for delay in sorted(rng.uniform(0.05, 0.95, count)):
            in_force = SCALE.u_to_tension(rng.uniform(2.5, 3.5))
            commands.append((EPOCH + k * PERIOD + delay * PERIOD, in_force))
        applied[k] = in_force
    plant_u = np.where(np.isnan(applied), 3.0, SCALE.tension_to_u(np.nan_to_num(applied)))
    x0 = rng.uniform(-0.05, 0.05, (1, 4))
    x = dynamics.rollout(x0, plant_u[None], H, 10)[0]
    return x, SCALE.tension_to_u(applied), sorted(commands)


def write_hardware_bag(directory, x, commands, stamps=None):
    """The states (stamped `stamps`, default the sample times; recorded 1 ms later) and the
    commands (step 0: hardware has no step), written by rosbags into an MCAP bag."""
    store = installed_typestore()
    stamps = EPOCH + np.arange(len(x)) * PERIOD if stamps is None else stamps
    state_type, command_type = 'tsr_msgs/msg/TsrState', 'tsr_msgs/msg/TensionCommand'
    messages = []
    for k, (state, stamp) in enumerate(zip(SCALE.state_to_si(x), stamps)):
        msg = store.types[state_type](
            header=_stamp(store, stamp), step=k, run=0, theta=state[0], theta_rate=state[1],
            length=state[2], length_rate=state[3], has_out_of_plane=False, beta=0.0,
            beta_rate=0.0)
        messages.append((EPOCH + k * PERIOD + 1e-3, state_type, msg))
    for seconds, tension in commands:
        msg = store.types[command_type](header=_stamp(store, seconds), step=0,
                                        tension=float(tension), hold=False)
        messages.append((seconds, command_type, msg))
    with Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {name: writer.add_connection(f'/{topic}', name, typestore=store)
                       for topic, name in ((wire.STATE_TOPIC, state_type),
                                           (wire.TENSION_TOPIC, command_type))}
        for seconds, name, msg in sorted(messages, key=lambda m: m[0]):
            writer.write(connections[name], int(round(seconds * 1e9)),
                         store.serialize_cdr(msg, name))
    return directory


def _stamp(store, seconds):
    sec = math.floor(seconds)
    return store.types['std_msgs/msg/Header'](
        stamp=store.types['builtin_interfaces/msg/Time'](
            sec=sec, nanosec=int(round((seconds - sec) * 1e9)) % 10 ** 9), frame_id='orbit')


@pytest.fixture(scope='module')
def hardware_bag(tmp_path_factory):
    x, u, commands = hardware_loop(200)
    path = write_hardware_bag(tmp_path_factory.mktemp('hw') / 'hardware', x, commands)
    return path, x, u, commands


def test_the_bag_holds_only_the_two_topics_as_rosbags_wrote_them(hardware_bag):
    path = hardware_bag[0]
    reader = bag.BagReader(str(path))
    topics = {m.topic for m in reader.messages()}
    assert topics == {'/tsr/state', '/tsr/tension_cmd'}
    assert (path / 'metadata.yaml').exists() and not any(t.endswith('run_info') for t in topics)


def test_windows_are_the_states_and_the_tension_in_force_over_each_sample(hardware_bag):
    """Units from the options, the period from the stamps (10 s = 0.01 tau in these units),
    each sample's tension the last command received before the next state: two in a sample,
    the later; none, the previous one holding; the one sent before the first state is not
    in force (the run starts with none: sample 0 is a gap)."""
    path, x, u, commands = hardware_bag
    windows = recorded.read_windows(path, steps=30, stride=1, h=H, state_dim=4, scale=SCALE)
    prov = windows.provenance
    assert (prov['h_source'], prov['match'], prov['units']) == ('stamps', 'time', 'given')
    assert prov['sample_period_s'] == pytest.approx(PERIOD) and prov['h'] == H
    assert prov['gaps']['missing_commands'] == 1 and prov['gaps']['transitions'] == 198
    assert len(windows.data) == 198 - 30 + 1
    for k, (xs, us) in enumerate(zip(windows.data.x, windows.data.u)):
        np.testing.assert_allclose(xs, x[1 + k:1 + k + 31], rtol=0, atol=1e-9)
        np.testing.assert_allclose(us, u[1 + k:1 + k + 30], rtol=0, atol=1e-12)
    (line,) = windows.warnings[:1]
    assert line == (f'{path}: no simulator RunInfo: units as given (orbit rate 0.001 rad/s, '
                    'tether 50000 m, mass 35 kg), sample period 10 s = 0.01 tau from the '
                    "states' stamps, commands matched by time")
    loop = bag.read_loop(path, scale=SCALE)
    assert loop.counts['commands'] == len(commands) and loop.match == 'time'
    # Matched by step, every command (step 0) would answer state 0 alone.
    by_step = bag.read_loop(path, scale=SCALE, match='step')
    assert np.isfinite(by_step.u).sum() == 1


def test_the_sample_period_from_an_option_or_from_the_stamps_and_a_clear_line_when_none(
        hardware_bag, tmp_path):
    path, x, u, commands = hardware_bag
    # In the paper's units 10 s is another h than the model's: refused in one line.
    with pytest.raises(recorded.BagDataError) as caught:
        recorded.read_windows(path, steps=30, h=H)
    assert str(caught.value) == (f"{path}: sample period h = 0.011804 tau (10 s, from the "
                                 "states' stamps); the model needs 0.01 tau = 8.4717 s within "
                                 '0.10%')
    # Stamps that give no period (a clock never set): the option gives it, and the warning
    # counts the stamp intervals that do not bear it out.
    flat = write_hardware_bag(tmp_path / 'flat', x, commands, stamps=np.zeros(len(x)))
    with pytest.raises(recorded.BagDataError, match='sample period unknown: no simulator '
                       "RunInfo, and the states' header stamps do not give one"):
        recorded.read_windows(flat, steps=30, scale=SCALE)
    windows = recorded.read_windows(flat, steps=30, h=H, scale=SCALE, sample_period=PERIOD)
    assert windows.provenance['h_source'] == 'option' and len(windows.data) == 6
    assert f'{flat}: 199 of 199 sample intervals of the states\' stamps differ from h by more ' \
        'than 10%' in windows.warnings
    with pytest.raises(ValueError, match='sample_period must be a finite number of seconds'):
        recorded.read_windows(flat, steps=30, sample_period=-1.0)
    with pytest.raises(ValueError, match='match must be one of step, time'):
        bag.read_runs(flat, match='sideways')


def test_bag_runs_prints_the_loop_as_read_with_the_options(hardware_bag, capsys):
    path = hardware_bag[0]
    assert bag_tool.main(['runs', str(path), *UNITS]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1:] == [
        'loop:       /',
        'units:      orbit rate 0.001 rad/s, tether 50000 m, mass 35 kg (as given)',
        "sample:     h = 0.01 tau = 10 s (from the states' stamps)",
        'commands:   matched by time',
        'runs:       1',
        f'  run 0: steps 0-199 (200 states): {len(hardware_bag[3])} commands, 198 of 199 '
        'samples with a tension']
    assert bag_tool.main(['runs', str(path), '--mass', '-3']) == 2
    assert capsys.readouterr().err.count('\n') == 1


def test_retrain_on_a_hardware_bag_end_to_end(hardware_bag, tmp_path, capsys):
    path = hardware_bag[0]
    out = tmp_path / 'model'
    code = retrain.main([
        '--bags', str(path), '--out', str(out), '--config-json', json.dumps(TINY),
        '--test-trajectories', '40', *UNITS])
    printed, err = capsys.readouterr()
    assert code == 0, err
    assert f'{path}: ' in printed and 'windows' in printed
    assert 'no simulator RunInfo: units as given' in err
    info = json.loads((out / 'model.json').read_text())['retrain']
    (entry,) = info['bags']
    assert entry['messages'] == {'/tsr/state': 200, '/tsr/tension_cmd': len(hardware_bag[3])}
    assert entry['windows'] > 0 and info['recorded_windows'] == entry['windows']
    # Without the hardware's units the period is another h: one line, exit 2.
    code = retrain.main(['--bags', str(path), '--out', str(tmp_path / 'other'),
                         '--config-json', json.dumps(TINY), '--test-trajectories', '40'])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f'retrain: {path}: sample period h = 0.011804 tau')
    for bad in (['--sample-period', '0'], ['--match-commands', 'sideways']):
        with pytest.raises(SystemExit) as caught:
            retrain.main(['--bags', str(path), '--out', str(tmp_path / 'x'), *bad])
        assert caught.value.code == 2


# --------------------------------------------------------------------------- timed, by time

def timed_bag(directory, messages):
    """A timed simulator's loop (RunInfo mode timed) with `messages` (topic, cdr) after it."""
    with bag.BagWriter(str(directory)) as writer:
        for name, type_name in (('/tsr/run_info', 'tsr_msgs/msg/RunInfo'),
                                ('/tsr/state', 'tsr_msgs/msg/TsrState'),
                                ('/tsr/tension_cmd', 'tsr_msgs/msg/TensionCommand'),
                                ('/tsr/sim_status', 'tsr_msgs/msg/SimStatus')):
            writer.add_topic(topic(name, type_name))
        messages = [('/tsr/run_info', run_info_cdr('simulator', simulator_info(
            mode='timed')))] + messages
        for i, (name, data) in enumerate(messages):
            # On sim time a reset sends the log time back: the order recorded is what counts.
            writer.write(name, data, log_time_ns=10 ** 6 * (1 + i % 5))
    return directory


def status(run, holding, step=0):
    return ('/tsr/sim_status', _cdr('tsr_msgs/msg/SimStatus', header=_header(0.0), status=0,
                                    message='', step=step, run=run, holding=holding,
                                    commands_accepted=0, rejected_non_finite=0,
                                    rejected_negative=0, rejected_over_limit=0,
                                    rejected_stale=0, command_timeouts=0))


def test_timed_commands_are_held_until_a_hold_and_a_reset_starts_without_one(tmp_path):
    """Run 0: a command answering step 0 arrives after state 1 (late: in force from sample 1
    on); a hold command (the controller stopped) leaves samples without tension until the
    next command; a status saying the plant holds does too. Run 1 (after a reset): its first
    sample has no tension in force, whatever run 0 ended with."""
    x = np.zeros((12, 4))
    x[:, 2] = -0.5 + 0.01 * np.arange(12)

    def state(k, run=0):
        return ('/tsr/state', state_cdr(x[k], k, run=run))

    def command(u, step=0, hold=False):
        return ('/tsr/tension_cmd', tension_cdr(u, step, hold=hold))
    messages = [state(0), state(1), command(3.0), state(2), command(3.1, 2), state(3),
                command(2.9, hold=True), state(4), state(5), command(3.2, 5), state(6),
                status(0, True), state(7), command(3.3), state(8),
                state(0, 1), state(1, 1), command(3.4), state(2, 1), state(3, 1)]
    first, second = bag.read_runs(timed_bag(tmp_path / 'b', messages))
    assert first.match == 'time' and (first.sim_run, second.sim_run) == (0, 1)
    nan = np.nan
    np.testing.assert_allclose(first.u, [nan, 3.0, 3.1, nan, nan, 3.2, nan, 3.3, 3.3],
                               rtol=0, atol=1e-12)
    assert first.held.tolist() == [False, False, False, True, True, False, True, False, False]
    np.testing.assert_allclose(second.u, [nan, 3.4, 3.4, 3.4], rtol=0, atol=1e-12)
    assert (first.counts['commands'], second.counts['commands']) == (5, 1)
    windows = recorded.read_windows(tmp_path / 'b', steps=1)
    gaps = windows.provenance['gaps']
    assert (gaps['held_steps'], gaps['missing_commands'], gaps['windows']) == (3, 2, 6)
