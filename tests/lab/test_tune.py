"""The tuning command: the law's own settings first, a study that resumes, held-out scoring."""

import contextlib
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tsr_koopman_ctrl.control import LinearisedLqr
from tsr_koopman_ctrl.evaluation import closed_loop_figures, COMPARISON_STARTS
from lab import tune, tuning
from lab.tuning import scoring, space, workers
import postgres_server


def test_a_study_resumes_and_reports_on_held_out_starts(tmp_path):
    args = ['--law', 'linear_lqr', '--steps', '1000', '--out', str(tmp_path)]
    assert tune.main([*args, '--trials', '2']) == 0
    assert tune.main([*args, '--trials', '4', '--jobs', '2']) == 0     # resumes the journal
    summary = json.loads((tmp_path / 'linear_lqr_swing0.8.json').read_text())
    assert summary['trials'] >= 4
    # The first trial is the law's own settings, so the best is never worse than the default.
    default = summary['results']['tuning_default']['score']
    assert summary['best_value'] <= default
    assert len(summary['results']['held_out_tuned']['runs']) == 5
    # The report's figures are the closed loop's own.
    first = closed_loop_figures(LinearisedLqr(), COMPARISON_STARTS[0], 1000)
    assert summary['results']['tuning_default']['runs'][0]['settle_tau'] == first['settle_tau']


def test_the_laws_own_settings_are_a_trial_with_several_workers(tmp_path):
    """Two workers on a fresh study: the default is enqueued before either starts (a worker
    that checked for an empty study itself lost that race to its sibling)."""
    import optuna
    args = ['--law', 'linear_lqr', '--steps', '200', '--out', str(tmp_path)]
    assert tune.main([*args, '--trials', '2', '--jobs', '2']) == 0
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(
        str(tmp_path / 'linear_lqr_swing0.8.journal')))
    study = optuna.load_study(study_name='linear_lqr_swing0.8', storage=storage)
    assert space.as_params('linear_lqr', {}) in [t.params for t in study.trials]


def test_the_search_space_comes_from_the_settings_classes():
    import optuna
    trial = optuna.trial.FixedTrial({'q_0': 2.0, 'q_1': 3.0, 'q_2': 4.0, 'q_3': 5.0, 'r': 0.5})
    assert space.suggest(trial, 'linear_lqr') == {'q': (2.0, 3.0, 4.0, 5.0), 'r': 0.5}
    assert set(space.as_params('koopman_mpc', {})) == {'horizon', 'r', 'q_0', 'q_1', 'q_2',
                                                       'q_3'}
    # The state weight's cross terms only when asked (--also), six of them.
    params = space.as_params('linear_lqr', {}, also=('q_cross',))
    assert {f'q_cross_{i}' for i in range(6)} <= set(params)
    assert all(params[f'q_cross_{i}'] == 0.0 for i in range(6))


def test_also_names_a_searchable_setting(tmp_path, capsys):
    args = ['--law', 'linear_lqr', '--steps', '300', '--out', str(tmp_path), '--trials', '1']
    assert tune.main([*args, '--also', 'q_cross']) == 0
    summary = json.loads((tmp_path / 'linear_lqr_with-q_cross_swing0.8.json').read_text())
    assert len(summary['best_settings']['q_cross']) == 6
    assert tune.main([*args, '--also', 'horizon']) == 2
    assert '--also horizon: linear_lqr has no such searchable setting' in \
        capsys.readouterr().err


@pytest.mark.parametrize('settings, expected', [({'r': -1.0}, scoring.PENALTY_TAU)])
def test_a_law_that_cannot_be_built_scores_the_penalty(settings, expected):
    assert scoring.score('linear_lqr', settings, COMPARISON_STARTS[:1], 0.8, 100)[0] == expected


def test_the_ratio_objectives_score_the_frontier_ratio_at_each_runs_swing():
    starts = COMPARISON_STARTS[:2]
    mean, runs = scoring.score('linear_lqr', {}, starts, 0.8, 1000, 'ratio')
    worst, _ = scoring.score('linear_lqr', {}, starts, 0.8, 1000, 'worst-ratio')
    # Recomputed from the frontier table directly, not from the figures' own ratio.
    from tsr_koopman_ctrl.evaluation.frontier import frontier_tau
    ratios = [r['settle_tau'] / frontier_tau(s, r['swing']) for s, r in zip(starts, runs)]
    assert mean == pytest.approx(sum(ratios) / 2) and worst == pytest.approx(max(ratios))
    assert worst > mean
    # A swing bound the runs break scores the ratio penalty, not the settle one.
    assert scoring.score('linear_lqr', {}, starts, 0.1, 1000, 'ratio')[0] == scoring.PENALTY_RATIO


def test_a_study_keeps_its_objective_and_names_it(tmp_path, capsys):
    args = ['--law', 'linear_lqr', '--steps', '300', '--out', str(tmp_path), '--trials', '1']
    assert tune.main([*args, '--objective', 'worst-ratio']) == 0
    assert (tmp_path / 'linear_lqr_worst-ratio_swing0.8.json').exists()
    journal = str(tmp_path / 'linear_lqr_worst-ratio_swing0.8.journal')
    # The same journal and study under another objective: one line, exit 2, no trial run and
    # the journal as it was (create_study appended a record even for a study it loaded).
    before = open(journal, 'rb').read()
    assert tune.main([*args, '--objective', 'settle', '--storage', journal,
                      '--study', 'linear_lqr_worst-ratio_swing0.8']) == 2
    assert 'was tuned on --objective worst-ratio, not settle' in capsys.readouterr().err
    assert open(journal, 'rb').read() == before


def test_the_swing_objective_scores_the_largest_swing_of_settled_runs():
    starts = COMPARISON_STARTS[:2]
    value, runs = scoring.score('linear_lqr', {}, starts, 0.1, 1000, 'swing')
    assert value == max(r['swing'] for r in runs) and value > 0.1   # the bound plays no part
    assert scoring.score('linear_lqr', {'r': -1.0}, starts, 0.8, 100, 'swing')[0] == \
        scoring.PENALTY_SWING
    # 30 steps settle nowhere: every start scores the penalty.
    assert scoring.score('linear_lqr', {}, starts, 0.8, 30, 'swing')[0] == scoring.PENALTY_SWING


def test_the_graded_penalty_grows_with_how_far_a_run_missed():
    starts = COMPARISON_STARTS[:2]
    # The same runs, flat and graded: under a 0.1-rad bound both starts swing past it.
    flat, runs = scoring.score('linear_lqr', {}, starts, 0.1, 1000, 'worst-ratio')
    graded, _ = scoring.score('linear_lqr', {}, starts, 0.1, 1000, 'worst-ratio', graded=True)
    assert flat == scoring.PENALTY_RATIO
    past = max(r['swing'] for r in runs) - 0.1     # every run settled, so no unsettled 1
    assert all(r['settle_tau'] is not None for r in runs) and past > 0.3
    assert graded == pytest.approx(scoring.PENALTY_RATIO + past)
    # A looser bound misses by less and scores less; a run within it scores its ratio.
    looser, _ = scoring.score('linear_lqr', {}, starts, 0.3, 1000, 'worst-ratio', graded=True)
    assert scoring.PENALTY_RATIO < looser < graded
    within, _ = scoring.score('linear_lqr', {}, starts, 0.8, 1000, 'worst-ratio', graded=True)
    assert within == scoring.score('linear_lqr', {}, starts, 0.8, 1000, 'worst-ratio')[0] < 2.0
    # 30 steps settle nowhere (one each), a law that cannot be built scores the cap.
    assert scoring.score('linear_lqr', {}, starts, 0.8, 30, 'settle', graded=True)[0] == \
        scoring.PENALTY_TAU + 1.0
    assert scoring.score('linear_lqr', {'r': -1.0}, starts, 0.8, 30, 'settle', graded=True)[0] == \
        scoring.PENALTY_TAU + scoring.MISS_CAP


def test_a_study_keeps_its_penalty_and_names_it(tmp_path, capsys):
    args = ['--law', 'linear_lqr', '--steps', '300', '--out', str(tmp_path), '--trials', '1',
            '--swing-max', '0.1']
    assert tune.main([*args, '--penalty', 'graded']) == 0
    summary = json.loads((tmp_path / 'linear_lqr_graded_swing0.1.json').read_text())
    assert summary['penalty'] == 'graded' and summary['best_value'] > scoring.PENALTY_TAU
    assert 'the trial that missed least' in capsys.readouterr().out
    journal = str(tmp_path / 'linear_lqr_graded_swing0.1.journal')
    assert tune.main([*args, '--storage', journal, '--study', 'linear_lqr_graded_swing0.1']) == 2
    assert 'was tuned on --penalty graded, not flat' in capsys.readouterr().err


def test_swing_starts_tune_on_six_starts_and_the_study_keeps_them(tmp_path, capsys):
    from tsr_koopman_ctrl.evaluation import frontier_tau, HELD_OUT_STARTS
    from tsr_koopman_ctrl.evaluation.starts import SWING_TUNING_STARTS
    # The two extra starts begin with a swing, are no held-out start, and have frontier rows.
    assert all(start[0] != 0.0 and start[1] != 0.0 for start in SWING_TUNING_STARTS)
    assert not set(SWING_TUNING_STARTS) & set(HELD_OUT_STARTS + COMPARISON_STARTS)
    assert all(frontier_tau(start, 0.8) is not None for start in SWING_TUNING_STARTS)
    args = ['--law', 'linear_lqr', '--steps', '1000', '--out', str(tmp_path), '--trials', '1',
            '--objective', 'worst-ratio']
    assert tune.main([*args, '--starts', 'swing']) == 0
    summary = json.loads(
        (tmp_path / 'linear_lqr_worst-ratio_swing-starts_swing0.8.json').read_text())
    assert summary['starts'] == 'swing'
    assert summary['tuning_starts'] == [list(s) for s in COMPARISON_STARTS + SWING_TUNING_STARTS]
    runs = summary['results']['tuning_default']['runs']
    assert len(runs) == 6 and len(summary['results']['held_out_default']['runs']) == 5
    # The score is the largest ratio over all six, the swing starts' included.
    extra = [closed_loop_figures(LinearisedLqr(), s, 1000) for s in SWING_TUNING_STARTS]
    assert [r['settle_tau'] for r in runs[4:]] == [f['settle_tau'] for f in extra]
    assert summary['best_value'] == max(r['frontier_ratio'] for r in runs)
    journal = str(tmp_path / 'linear_lqr_worst-ratio_swing-starts_swing0.8.journal')
    capsys.readouterr()
    assert tune.main([*args, '--storage', journal,
                      '--study', 'linear_lqr_worst-ratio_swing-starts_swing0.8']) == 2
    assert 'was tuned on --starts swing, not comparison' in capsys.readouterr().err


@contextlib.contextmanager
def _tune_running(tmp_path, trials=100000):
    """`lab.tune` started in a process group of its own (the command and its workers); the
    group is killed on the way out, whatever happened in between."""
    # SIGINT as a terminal delivers it: a test run started in the background (`.ci/run &`)
    # inherits SIGINT ignored, which Python then leaves ignored.
    proc = subprocess.Popen(
        [sys.executable, '-m', 'lab.tune', '--law', 'linear_lqr', '--steps',
         '200', '--trials', str(trials), '--jobs', '2', '--out', str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        yield proc
    finally:
        _stop_group(proc)


def _stop_group(proc):
    """Kill whatever of `proc`'s process group still runs and read its output: (out, err).
    Killed first, so that reading cannot wait for a command that does not end."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    return proc.communicate()


def _journal_size_once_trials_run(tmp_path, proc, timeout=60.0):
    journal = tmp_path / 'linear_lqr_swing0.8.journal'
    deadline = time.monotonic() + timeout
    while not journal.exists() or journal.stat().st_size < 20000:    # several trials in
        if proc.poll() is not None or time.monotonic() > deadline:
            _, err = _stop_group(proc)
            pytest.fail(f'no trials in {journal} after {timeout} s (tune exited with '
                        f'{proc.returncode}):\n{err}')
        time.sleep(0.2)
    return journal


def test_ctrl_c_lets_the_trials_in_progress_finish_and_says_how_to_resume(tmp_path):
    """Ctrl-C reaches the command and its workers (one process group). Before: five
    tracebacks, and the trials in progress stored as FAIL, which counted against --trials."""
    import collections

    import optuna
    with _tune_running(tmp_path) as proc:
        journal = _journal_size_once_trials_run(tmp_path, proc)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert 'Traceback' not in err and 'finishing the trials in progress' in err
    assert f'tune: interrupted; {journal} keeps the finished trials' in err
    storage = optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(journal)))
    study = optuna.load_study(study_name='linear_lqr_swing0.8', storage=storage)
    states = collections.Counter(t.state.name for t in study.trials)
    assert set(states) == {'COMPLETE'} and states['COMPLETE'] > 2, states


def test_killing_the_command_stops_its_workers(tmp_path):
    """The workers went on filling the journal, unseen, after their command was killed."""
    with _tune_running(tmp_path) as proc:
        journal = _journal_size_once_trials_run(tmp_path, proc)
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=10)
        time.sleep(3.0)                  # a 200-step linear_lqr trial takes well under that
        size = journal.stat().st_size
        time.sleep(3.0)
        alive = _group_alive(proc.pid)
    assert journal.stat().st_size == size and not alive


def _group_alive(group):
    try:
        os.killpg(group, 0)
        return True
    except ProcessLookupError:
        return False


# ---------------------------------------------------------------------------------------------
# A study in a database: a real PostgreSQL server (tests/lab/postgres_server.py), two workers.

@pytest.fixture
def postgres(tmp_path):
    """A PostgreSQL server with its data in tmp_path, on a free port, stopped at teardown
    whatever the test did."""
    with postgres_server.started(tmp_path / 'postgres') as server:
        yield server


def _rows(server):
    """Every row of every table in the server's database: the storage as it is."""
    import psycopg
    with psycopg.connect(server.url) as connection:
        tables = [name for (name,) in connection.execute(
            "SELECT table_name FROM information_schema.tables WHERE table_schema = 'public' "
            'ORDER BY table_name')]
        return {table: sorted(map(repr, connection.execute(f'SELECT * FROM {table}')))
                for table in tables}


def test_two_workers_on_a_postgres_study_store_every_trial_once_and_the_best_deploys(
        postgres, tmp_path, capsys):
    import collections

    import optuna
    from tsr_koopman_ctrl.control import closed_loop, make_controller
    from tsr_koopman_ctrl.evaluation import PAPER_START, run_figures
    from tsr_sim.dynamics import PAPER_STEP
    result = tuning.tune('linear_lqr', trials=4, jobs=2, storage=postgres.url, steps=1000,
                         out=str(tmp_path), progress=False)
    study = optuna.load_study(study_name=result.study, storage=postgres.url)
    # Each trial once, none lost, none past --trials: the four asked for, numbered 0..3, each
    # with its settings, run by both workers (two each).
    assert collections.Counter(t.state.name for t in study.trials) == {'COMPLETE': 4}
    assert sorted(t.number for t in study.trials) == list(range(4))
    assert all('settings' in t.user_attrs for t in study.trials)
    ran_by = collections.Counter(t.user_attrs['worker'] for t in study.trials)
    assert sorted(ran_by.values()) == [2, 2], ran_by
    assert space.as_params('linear_lqr', {}) in [t.params for t in study.trials]
    assert result.trials == 4 and result.best_value == study.best_value
    assert result.settings == space.from_json(study.best_trial.user_attrs['settings'])
    summary = json.loads((tmp_path / 'linear_lqr_swing0.8.json').read_text())
    assert summary['best_settings'] == study.best_trial.user_attrs['settings']
    # The best settings deploy: the law they build settles from the paper's start.
    states, tensions = closed_loop(make_controller('linear_lqr', **result.settings),
                                   PAPER_START, 2000)
    figures = run_figures(np.arange(len(states)) * PAPER_STEP, states, tensions,
                          start=PAPER_START, halted=len(states) <= 2000)
    assert figures['settle_tau'] is not None and figures['swing'] <= 0.8
    # Another objective on the same study: refused in one line, the database as it was.
    before = _rows(postgres)
    capsys.readouterr()
    assert tune.main(['--law', 'linear_lqr', '--steps', '1000', '--trials', '5',
                      '--objective', 'worst-ratio', '--study', result.study,
                      '--storage', postgres.url, '--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'was tuned on --objective settle, not worst-ratio' in err
    assert _rows(postgres) == before


def test_a_worker_killed_mid_trial_leaves_the_postgres_study_usable(postgres, tmp_path):
    """SIGKILL to one of two workers while a trial of its runs: the command fails, the dead
    trial stays RUNNING (it does not count), and the same command resumes the study to the
    trials asked for."""
    import collections

    import optuna
    argv = ['--law', 'linear_lqr', '--steps', '300', '--trials', '8', '--jobs', '2',
            '--storage', postgres.url, '--out', str(tmp_path)]
    proc = subprocess.Popen([sys.executable, '-m', 'lab.tune', *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        killed = _kill_a_worker_mid_trial(postgres.url, proc)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            _stop_group(proc)
    assert proc.returncode == 1 and 'a tuning worker failed' in err, err
    study = optuna.load_study(study_name='linear_lqr_swing0.8', storage=postgres.url)
    assert study.trials[killed].state.name == 'RUNNING'
    complete = sum(t.state.name == 'COMPLETE' for t in study.trials)
    assert complete < 8
    # The same command resumes: the trials asked for, the dead one left as it was.
    assert tune.main(argv) == 0
    study = optuna.load_study(study_name='linear_lqr_swing0.8', storage=postgres.url)
    states = collections.Counter(t.state.name for t in study.trials)
    assert states == {'COMPLETE': 8, 'RUNNING': 1}, states
    assert study.trials[killed].state.name == 'RUNNING'
    summary = json.loads((tmp_path / 'linear_lqr_swing0.8.json').read_text())
    assert summary['trials'] == 8 and summary['best_value'] == study.best_value


def _kill_a_worker_mid_trial(url, proc, timeout=240.0):
    """The number of a trial whose worker was SIGKILLed while it ran: the worker is stopped
    (SIGSTOP) first, so that its trial cannot end between the look and the kill."""
    import optuna
    deadline = time.monotonic() + timeout
    storage = None
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            _, err = proc.communicate()
            pytest.fail(f'tune exited with {proc.returncode} before a trial ran:\n{err}')
        if storage is None and _has_tables(url):
            storage = optuna.storages.RDBStorage(url)     # one engine, not one a look
        names = optuna.study.get_all_study_names(storage) if storage else []
        trials = optuna.load_study(study_name=names[0], storage=storage).trials if names else []
        running = [t for t in trials if t.state.name == 'RUNNING' and 'worker' in t.user_attrs]
        if running:
            trial = running[0]
            pid = int(trial.user_attrs['worker'].rsplit(':', 1)[1])
            os.kill(pid, signal.SIGSTOP)
            study = optuna.load_study(study_name=names[0], storage=storage)
            if study.trials[trial.number].state.name == 'RUNNING':
                os.kill(pid, signal.SIGKILL)
                return trial.number
            os.kill(pid, signal.SIGCONT)       # it had just finished: another look
        time.sleep(0.2)
    raise AssertionError(f'no trial ran in {timeout:g} s')


def _has_tables(url):
    """Whether the command has made optuna's schema: its alembic stamp is the last thing
    written (an RDBStorage opened before that races the command to create the same table)."""
    import psycopg
    with psycopg.connect(url) as connection:
        if connection.execute("SELECT to_regclass('public.alembic_version')").fetchone()[0] \
                is None:
            return False
        return connection.execute('SELECT COUNT(*) FROM alembic_version').fetchone()[0] > 0


def test_a_sqlite_study_resumes_and_a_refusal_leaves_the_file_alone(tmp_path, capsys):
    import sqlite3
    database = tmp_path / 'tune.db'
    args = ['--law', 'linear_lqr', '--steps', '300', '--out', str(tmp_path), '--trials', '1',
            '--storage', f'sqlite:///{database}']
    assert tune.main([*args, '--penalty', 'graded']) == 0
    assert tune.main([*args, '--penalty', 'graded', '--trials', '2']) == 0   # resumes
    before = database.read_bytes()
    assert tune.main([*args, '--study', 'linear_lqr_graded_swing0.8']) == 2
    assert 'was tuned on --penalty graded, not flat' in capsys.readouterr().err
    assert database.read_bytes() == before
    with sqlite3.connect(database) as connection:
        assert connection.execute("SELECT COUNT(*) FROM trials WHERE state = 'COMPLETE'"
                                  ).fetchone() == (2,)


def test_a_database_out_of_reach_is_one_line_without_its_password(tmp_path, capsys):
    port = postgres_server.free_port()      # nothing listens there
    url = f'postgresql://tune:hunter2@127.0.0.1:{port}/optuna'
    assert tune.main(['--law', 'linear_lqr', '--storage', url, '--out', str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'cannot open the database' in err
    assert f'postgresql://tune:***@127.0.0.1:{port}/optuna' in err and 'hunter2' not in err
    assert list(tmp_path.iterdir()) == []


def test_the_remaining_trials_are_shared_among_the_workers():
    assert workers.shares(7, 3) == [3, 2, 2]
    assert workers.shares(1, 2) == [1]
    assert workers.shares(6, 2) == [3, 3]
