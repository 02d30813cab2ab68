"""deploy without processes: what it refuses before any node starts, how it reports a run that
halted or failed, and its table. Runs are bags written here (`tests/learning/test_recorded`'s
writer), halted with the simulator's own messages (`tsr_sim.plant.Plant`)."""

import pathlib
import sys
import types

import numpy as np
import pytest
from tsr_sim import dynamics
from tsr_sim.plant import config_from_parameters, Plant, Status
from tsr_sim.units import Scale

from tsr_koopman_ctrl import bag
from tsr_koopman_ctrl.bag.checks import find_bags, is_failed
from tsr_koopman_ctrl.commands import deploy, retrain
from tsr_koopman_ctrl.deployment import (COLUMNS, Deployment, DeploymentError, read_result,
                                         summary_table)
from tsr_koopman_ctrl.learning import distributed, retraining

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / 'learning'))
from test_recorded import (_cdr, _header, lockstep, loop_data,  # noqa: E402
                           write_messages)


def deploy_argv(tmp_path, *extra, law='linear_lqr'):
    return ['--out', str(tmp_path / 'out'), '--bags', str(tmp_path / 'bags'), '--law', law,
            *extra]


def exit_status(argv):
    try:
        return deploy.main(argv)
    except SystemExit as stop:
        return stop.code


# --------------------------------------------------------------------------- refused at once

@pytest.mark.parametrize('x0, message', [
    (['0', '0', '-1', '0.5'], 'outside the model domain: l = 0, not in (0, 2] (the third value '
     "is l - 1: the paper's start l = 0.01 is -0.99)"),
    (['0', '0', '1.5', '0'], 'outside the model domain: l = 2.5, not in (0, 2]'),
    (['2', '0', '-0.99', '0.5'], 'outside the model domain: |theta| = 2 rad is past max_swing '
     '1.5708 (tumbling)'),
])
def test_a_start_the_simulator_would_refuse_or_halt_at_once_is_one_line(tmp_path, capsys, x0,
                                                                        message):
    assert exit_status(deploy_argv(tmp_path, '--x0', *x0)) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]        # after the usage
    assert last.startswith('deploy: error: x0 [') and message in last
    assert not (tmp_path / 'bags').exists()


def test_the_x0_layout_is_in_the_help_and_a_start_past_the_full_length_is_named(tmp_path,
                                                                                capsys):
    """`--x0 0 0 0.01 0.5`, read as l = 0.01, starts at l = 1.01: said in one line."""
    assert exit_status(['--help']) == 0
    assert 'the third value is l - 1, not l' in ' '.join(capsys.readouterr().out.split())
    args = deploy.parse_args(deploy_argv(tmp_path, '--x0', '0', '0', '0.01', '0.5'))
    args.deployment.reservation.release()
    assert args.deployment.x0 == [0.0, 0.0, 0.01, 0.5]
    assert capsys.readouterr().err == (
        '[deploy] note: --x0 starts at l = 1.01, past the full tether length (the third value '
        "is l - 1: the paper's l = 0.01 is -0.99)\n")
    deploy.parse_args(deploy_argv(tmp_path)).deployment.reservation.release()
    assert capsys.readouterr().err == ''          # the paper's start: no note


def test_a_setting_of_another_law_than_the_one_deployed_is_refused(tmp_path, capsys):
    assert exit_status(deploy_argv(tmp_path, '--set', 'koopman_lqr.r=0.1',
                                   law='koopman_nmpc')) == 2
    assert ('koopman_lqr.r: koopman_lqr is not the law deployed (koopman_nmpc); the sections '
            'that apply are koopman_nmpc, observer, excitation, supervisor, safety_filter'
            in capsys.readouterr().err)
    # The deployed law's own section and the sections around every law are taken.
    args = deploy.parse_args(deploy_argv(tmp_path, '--set', 'linear_lqr.r=0.5',
                                         '--set', 'observer.disturbance=none'))
    args.deployment.reservation.release()
    assert args.deployment.settings['linear_lqr'] == {'r': 0.5}


# --------------------------------------------------------------------------- the run's end

def halted_plant(initial_state):
    """A plant run open-loop at the equilibrium tension until it halts; its status."""
    plant = Plant(config_from_parameters({'initial_state': initial_state, 'substeps': 1}))
    tension = Scale().u_to_tension(dynamics.EQUILIBRIUM_TENSION)
    for _ in range(1000):
        plant.advance(tension)
        if plant.status is Status.HALTED_OUT_OF_DOMAIN:
            return plant
    raise AssertionError(f'{initial_state} did not halt')


def status_cdr(plant):
    return _cdr('tsr_msgs/msg/SimStatus', header=_header(0.0), status=int(plant.status),
                message=plant.message, step=plant.step_index, run=0, holding=False,
                commands_accepted=plant.step_index, rejected_non_finite=0, rejected_negative=0,
                rejected_over_limit=0, rejected_stale=0, command_timeouts=0)


def halted_bag(directory, plant):
    """A loop bag of the plant's steps up to its halt, ending with its status."""
    x, u, _ = loop_data(plant.step_index + 1)
    return write_messages(directory, lockstep(x, u) + [('/tsr/sim_status', status_cdr(plant))])


@pytest.mark.parametrize('start, reason', [
    ([1.4, 1.0, 0.0, 0.0], 'tumbled'),                  # swinging past the local horizontal
    ([0.0, 0.0, -0.99, -2.0], 'left the domain'),       # reeled in through l = 0
])
def test_a_tumble_is_reported_as_a_tumble_not_as_leaving_the_domain(
        tmp_path, capsys, monkeypatch, start, reason):
    plant = halted_plant(start)
    path = halted_bag(tmp_path / 'run', plant)
    loop = bag.read_loop(str(path))
    assert loop.halted and loop.halt_reason == reason
    result = read_result(str(path), 'linear_lqr', start, 2000)
    assert result.figures['halt_reason'] == reason
    tau = f'{loop.halt_tau:.2f}'
    assert f'| {reason} at tau {tau} |' in summary_table([result.figures])
    assert f'{reason} at tau {tau}' in '\n'.join(bag.runs(str(path)))
    # deploy's last line says it too, in the simulator's words.
    monkeypatch.setattr(Deployment, 'run', lambda self: result)
    assert deploy.main(deploy_argv(tmp_path)) == 1
    last = capsys.readouterr().err.strip().splitlines()[-1]
    said = plant.message.split(';')[0]
    assert last == f'[deploy] the run halted at tau {tau}: {reason} ({said})'
    assert ('tumbling' in said) == (reason == 'tumbled')


def test_a_failed_deployment_keeps_its_bag_marked_and_retrain_skips_it(
        tmp_path, capsys, monkeypatch):
    """The README's retrain(['bags/']) after a deploy that failed: the partial bag is kept for
    a look, but a directory of bags given to retrain skips it, with one line."""
    x, u, _ = loop_data(40)

    def start(self):          # the recorder had written part of a run when a node died
        write_messages(pathlib.Path(self.bag), lockstep(x, u))
        return self

    def wait(self):
        raise DeploymentError('tsr_controller exited early')
    monkeypatch.setattr(Deployment, 'start', start)
    monkeypatch.setattr(Deployment, 'wait', wait)
    assert deploy.main(deploy_argv(tmp_path)) == 1
    (failed,) = (tmp_path / 'bags').iterdir()
    assert is_failed(str(failed))
    err = capsys.readouterr().err
    assert '[deploy] failed: tsr_controller exited early' in err
    assert f'the bag of the failed run is kept in {failed}, marked failed' in err
    assert bag.read_loop(str(failed)).step.size == 40          # nothing lost
    # Below a directory it is skipped, with one line; named itself, it is read.
    good = write_messages(tmp_path / 'bags' / 'good', lockstep(x, u))
    skipped = []
    assert find_bags([tmp_path / 'bags'], skipped) == [str(good)]
    assert skipped == [f'skipped {failed}: the bag of a failed deployment '
                       '(failed_deployment.txt says why; name the bag itself to read it)']
    with pytest.warns(bag.BagWarning, match='the bag of a failed deployment'):
        assert find_bags([tmp_path / 'bags']) == [str(good)]
    assert find_bags([failed]) == [str(failed)]
    # retrain reads the directory so and says the line.
    said = []
    model = types.SimpleNamespace(h=dynamics.PAPER_STEP, state_dim=4)
    config = types.SimpleNamespace(model=model,
                                   training=types.SimpleNamespace(validation_fraction=0.0))
    found = retraining.read_bag_set([tmp_path / 'bags'], [], retraining.RetrainOptions(),
                                    config, distributed.Context(),
                                    lambda line, **_: said.append(line))
    assert found.train_paths == [str(good)]
    assert said[0] == f'retrain: warning: {skipped[0]}'
    # A directory holding only failed bags is no training data: retrain says so.
    only_failed = tmp_path / 'only_failed'
    only_failed.mkdir()
    failed.rename(only_failed / failed.name)
    assert retrain.main(['--bags', str(only_failed), '--out', str(tmp_path / 'model'),
                         '--quiet']) == 2
    err = capsys.readouterr().err
    assert f'{only_failed}: no bag below it but those of failed deployments (1 skipped)' in err


# --------------------------------------------------------------------------- the table

def test_the_table_says_swing_in_rad_and_compute_in_ms():
    row = {'controller': 'linear_lqr', 'x0': [0.0, 0.0, -0.99, 0.5], 'settle_tau': 4.5,
           'halted': False, 'halt_tau': None, 'steps': 2000, 'planned_steps': 2000,
           'final_state': [0.0, 0.0, 0.001, 0.0], 'swing': 0.6924, 'theta_min': -0.6924,
           'theta_max': 0.1, 'length_overshoot': 0.0092, 'tension_max': 4.612,
           'tension_integral': 60.0, 'compute_median_us': 1520.0, 'compute_p99_us': 5210.0,
           'frontier_tau': 3.8, 'frontier_ratio': 1.3158}
    header, _, line = summary_table([row]).splitlines()
    cells = dict(zip(header.strip('| ').split(' | '), line.strip('| ').split(' | ')))
    assert list(cells) == list(COLUMNS)
    assert cells['swing [rad]'] == '0.692' and cells['compute median / p99 [ms]'] == '1.52 / 5.21'
    assert cells['l overshoot'] == '0.92%' and cells['max u'] == '4.61'
    assert not any('[us]' in name or 'theta range' in name for name in cells)
    assert np.isclose(float(cells['ratio']), 1.32)
