"""Campaigns against a real local Dask cluster of 2 workers: the same rows whatever the number of
workers, a killed worker and a killed driver, replays, bad specs, the report's bounds.

Cheap laws (linear_lqr, koopman_lqr bare) and a few hundred steps; nothing here depends on how
long anything takes.
"""

import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import yaml

from tsr_koopman_ctrl.campaign import (Campaign, clopper_pearson, differences, load_spec,
                                       read_rows, replay, run_campaign)
from tsr_koopman_ctrl.campaign.rows import finished_pairs, ROWS_DIR, TIMING_COLUMNS
from tsr_koopman_ctrl.commands import campaign as command

SPEC = {
    'runs': 4, 'steps': 200, 'seed': 11, 'swing_limit': 0.72,
    'start': {'low': [-0.05, -0.1, -0.995, 0.3], 'high': [0.05, 0.1, -0.98, 0.7],
              'distribution': ['uniform', 'uniform', 'normal', 'uniform']},
    'plant': {'actuator_gain': {'low': 0.8, 'high': 1.2},
              'actuator_lag': {'low': 0.0, 'high': 0.05, 'distribution': 'normal'},
              'sensor_noise_std': 0.001},
    # The bare learned law: the safety filter decides by wall-clock deadlines, so its rows
    # depend on the machine's load.
    'laws': ['linear_lqr', {'law': 'koopman_lqr', 'label': 'koopman_bare',
                            'set': ['supervisor.fallback=none', 'safety_filter.backup=none']}],
}


@pytest.fixture(scope='module')
def cluster():
    from dask.distributed import Client, LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=':0') as local, Client(local) as client:
        yield local, client


@pytest.fixture(scope='module')
def two_worker_campaign(cluster, tmp_path_factory):
    out = str(tmp_path_factory.mktemp('campaign') / 'two')
    rows = run_campaign(Campaign.parse(SPEC), out, client=cluster[1], progress=False)
    return out, rows


def comparable(rows):
    return rows.drop(columns=list(TIMING_COLUMNS)).sort_values(['run', 'law']).reset_index(
        drop=True)


@pytest.mark.timeout(180)
def test_the_rows_are_the_same_with_one_and_two_workers(two_worker_campaign, tmp_path):
    out, two = two_worker_campaign
    one = run_campaign(Campaign.parse(SPEC), str(tmp_path / 'one'), workers=1, progress=False)
    assert len(two) == 8 and sorted(set(two['law'])) == ['koopman_bare', 'linear_lqr']
    assert comparable(one).equals(comparable(two))
    expected = ['run', 'seed', 'actuator_gain', 'actuator_lag', 'x0_0', 'x0_1', 'x0_2', 'x0_3',
                'law', 'settle_tau', 'swing', 'halted', 'compute_median_ms', 'corrections',
                'correction_sum', 'switches', 'frontier_ratio']
    assert [c for c in two.columns if c in expected] == expected
    # Paired: both laws flew the same dispersed case.
    per_run = two.groupby('run')[['seed', 'actuator_gain', 'x0_3']].nunique()
    assert (per_run == 1).all().all()
    assert os.path.isfile(os.path.join(out, 'report.md'))


def test_a_replayed_worst_case_equals_its_row(two_worker_campaign, capsys):
    out, rows = two_worker_campaign
    worst = rows.loc[rows['swing'].idxmax()]
    again, stored = replay(out, int(worst['run']), worst['law'])
    assert differences(again, stored) == []
    assert command.main(['replay', out, '--run', str(int(worst['run'])), '--law',
                         worst['law']]) == 0
    printed = capsys.readouterr().out
    assert f"swing: {again['swing']}" in printed and 'equal to its row' in printed
    report = open(os.path.join(out, 'report.md')).read()
    assert f'replay {out} --run {int(worst["run"])} --law {worst["law"]}' in report
    assert 'ros2 run tsr_koopman_ctrl deploy --law' in report and '--plant' in report


def test_the_spec_stored_reads_back_to_the_same_campaign_and_cases():
    campaign = Campaign.parse(SPEC)
    again = Campaign.parse(yaml.safe_load(yaml.safe_dump(campaign.as_dict())))
    assert again.as_dict() == campaign.as_dict()
    assert [again.case(r) for r in (3, 0)] == [campaign.case(r) for r in (3, 0)]
    assert campaign.case(0) != campaign.case(1)


def kill_a_worker_after_the_first_row(client, out, killed):
    while not finished_pairs(out):
        time.sleep(0.01)
    killed['rows before'] = len(finished_pairs(out))
    pids = client.run(os.getpid)
    busy = [address for address, tasks in client.processing().items() if tasks]
    address = (busy or list(pids))[0]
    os.kill(pids[address], signal.SIGKILL)
    killed['pid'] = pids[address]


@pytest.mark.timeout(180)
def test_a_worker_killed_mid_campaign_and_the_campaign_still_completes_each_run_once(
        cluster, tmp_path):
    local, client = cluster
    out = str(tmp_path / 'killed')
    spec = {'runs': 16, 'steps': 300, 'seed': 2, 'laws': ['linear_lqr'],
            'start': {'low': [0.0, 0.0, -0.99, 0.3], 'high': [0.01, 0.01, -0.98, 0.7]}}
    killed = {}
    killer = threading.Thread(target=kill_a_worker_after_the_first_row,
                              args=(client, out, killed))
    killer.start()
    rows = run_campaign(Campaign.parse(spec), out, client=client, progress=False,
                        report=False)
    killer.join()
    assert killed['rows before'] < 16
    assert killed['pid'] not in client.run(os.getpid).values()
    assert sorted(rows['run']) == list(range(16))
    assert len(os.listdir(os.path.join(out, ROWS_DIR))) == 16


@pytest.mark.timeout(240)
def test_a_driver_killed_and_resume_complete_with_no_run_lost_or_repeated(cluster, tmp_path):
    out = str(tmp_path / 'driver')
    argv = ['--law', 'linear_lqr', '--runs', '40', '--steps', '300', '--seed', '5',
            '--out', out]
    driver = subprocess.Popen([sys.executable, '-m', 'tsr_koopman_ctrl.commands.campaign',
                               *argv, '--workers', '2', '--no-progress'],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while len(finished_pairs(out)) < 2 and driver.poll() is None:
            assert time.monotonic() < deadline, 'no rows from the driver'
            time.sleep(0.01)
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait()
    finally:
        os.killpg(driver.pid, signal.SIGKILL)     # its workers, orphaned
        driver.stderr.close()
    before = finished_pairs(out)
    assert driver.returncode == -signal.SIGKILL and 2 <= len(before) < 40
    resumed = command.main([*argv, '--resume', '--address', cluster[0].scheduler_address,
                            '--no-progress'])
    assert resumed == 0
    rows = read_rows(out)
    assert sorted(rows['run']) == list(range(40)) and set(rows['law']) == {'linear_lqr'}
    # A resume that changes the campaign is refused.
    with pytest.raises(SystemExit) as refused:
        command.main([*argv[:-2], '--steps', '301', '--out', out, '--resume'])
    assert refused.value.code == 2


BAD_SPECS = {
    'unknown law': ({'laws': ['no_such_law']}, "unknown law 'no_such_law'"),
    'unknown setting': ({'laws': ['linear_lqr'], 'set': ['linear_lqr.nope=1']},
                        "no setting 'nope'"),
    'setting of the wrong type': ({'laws': ['linear_lqr'], 'set': ['linear_lqr.r=big']},
                                  'cannot read'),
    'unknown plant parameter': ({'laws': ['linear_lqr'],
                                 'plant': {'actuator_gian': {'low': 0.9, 'high': 1.1}}},
                                "did you mean 'actuator_gain'"),
    'negative count': ({'laws': ['linear_lqr'], 'runs': -3}, 'runs must be an integer >= 1'),
    'count of the wrong type': ({'laws': ['linear_lqr'], 'steps': 'many'},
                                'steps must be an integer'),
    'empty plant range': ({'laws': ['linear_lqr'],
                           'plant': {'actuator_gain': {'low': 1.1, 'high': 1.1}}},
                          'empty range'),
    'empty start range': ({'laws': ['linear_lqr'],
                           'start': {'low': [0, 0, -0.9, 0.5], 'high': [0, 0.1, -0.8, 0.6]}},
                          'empty range'),
    'plant range past the declared one': ({'laws': ['linear_lqr'],
                                           'plant': {'eccentricity': {'low': 0, 'high': 2}}},
                                          'eccentricity must be in'),
    'unknown key': ({'laws': ['linear_lqr'], 'rums': 3}, "did you mean 'runs'"),
    'a plant parameter the campaign sets': ({'laws': ['linear_lqr'], 'plant': {'seed': 3}},
                                            'set by the campaign'),
}


@pytest.mark.parametrize('spec, says', BAD_SPECS.values(), ids=list(BAD_SPECS))
def test_a_bad_spec_is_refused_in_one_line_before_any_run(spec, says, tmp_path, capsys):
    path = tmp_path / 'spec.yaml'
    path.write_text(yaml.safe_dump(spec))
    out = tmp_path / 'out'
    with pytest.raises(SystemExit) as refused:
        command.main(['--spec', str(path), '--out', str(out)])
    assert refused.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith('campaign: error: ') and says in last, last
    assert not out.exists()
    with pytest.raises(ValueError, match=says.replace('(', r'\(')):
        load_spec(str(path))


def test_bad_flags_are_refused_in_one_line(tmp_path, capsys):
    for argv in (['--runs', '-1'], ['--law', 'nope'], ['--set', 'linear_lqr.q'],
                 ['--set', 'koopman_mpc.horizon=5', '--law', 'linear_lqr']):
        with pytest.raises(SystemExit) as refused:
            command.main([*argv, '--out', str(tmp_path / 'out')])
        assert refused.value.code == 2
        assert capsys.readouterr().err.strip().splitlines()[-1].startswith('campaign: error:')
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('trials', [1, 7, 50, 1000])
def test_clopper_pearson_at_the_ends_has_the_closed_form(trials):
    assert clopper_pearson(0, trials) == pytest.approx((0.0, 1 - 0.025 ** (1 / trials)))
    assert clopper_pearson(trials, trials) == pytest.approx((0.025 ** (1 / trials), 1.0))


def test_clopper_pearson_against_a_published_value():
    # 5 of 10: the exact interval tabulated by Clopper and Pearson (1934), to 4 places.
    low, high = clopper_pearson(5, 10)
    assert (round(low, 4), round(high, 4)) == (0.1871, 0.8129)
    with pytest.raises(ValueError):
        clopper_pearson(3, 2)
