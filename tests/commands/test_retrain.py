"""The retrain command on tiny synthetic bags: provenance, held-out errors, bad bags, DDP."""

import hashlib
import json
import os
import pathlib
import shutil
import sys
import time

import numpy as np
import pytest
import torch
from torch import multiprocessing
from tsr_sim import dynamics

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / 'learning'))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / 'bag'))
from test_distributed import free_port  # noqa: E402
from test_rosbag2_style import stock_bag  # noqa: E402
from test_recorded import H, write_loop  # noqa: E402

from tsr_koopman_ctrl.learning import dataset as datasets  # noqa: E402
from tsr_koopman_ctrl.learning.trainer import save_model, Trainer  # noqa: E402
from tsr_koopman_ctrl.model import LiftedModel, model_file  # noqa: E402
from tsr_koopman_ctrl.commands import bag as bag_tool  # noqa: E402
from tsr_koopman_ctrl.commands import retrain  # noqa: E402
from tsr_koopman_ctrl.learning import retraining  # noqa: E402

TINY = {'lift_dim': 4, 'hidden': 16, 'layers': 2, 'input_hidden': 8, 'input_layers': 1,
        'input_terms': 3, 'batch_size': 32, 'learning_rate': 3e-3}


@pytest.fixture(scope='module', autouse=True)
def one_thread():
    """One torch thread for these tiny models: a second gains nothing, and on a loaded
    machine OpenMP threads waiting for each other made a 1 s training take a minute."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope='module')
def init_model(one_thread, tmp_path_factory):
    """A tiny model to fine-tune (2 epochs on 200 sampled trajectories)."""
    out = tmp_path_factory.mktemp('init')
    data, _ = datasets.sample(datasets.SamplingConfig(trajectories=200, seed=5))
    config = model_file.KoopmanConfig.from_dict({**TINY, 'epochs': 2})
    trainer = Trainer(config, progress=False)
    save_model(out, trainer.fit(data), config, trainer, data, data, 1.0, 'test',
               envelope=datasets.envelope(data))
    return out


def plant_bag(path, n, seed, **options):
    """A loop the dynamics really ran: near the equilibrium, tension 3 +- 0.5 (excitation);
    `options` for write_loop."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(-0.05, 0.05, 4)
    excitation = rng.choice([-0.5, 0.5], n)
    u = 3.0 + excitation
    x = dynamics.rollout(x0[None], u[None], H, 10)[0][:n]
    return write_loop(path, x, u, excitation=excitation, **options)


@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp('bags')
    return (plant_bag(root / 'train' / 'a', 160, 1), plant_bag(root / 'train' / 'b', 130, 2),
            plant_bag(root / 'held' / 'c', 100, 3))


def run(capsys, *argv):
    code = retrain.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def sha256_of(bag):
    return hashlib.sha256(b''.join(f.read_bytes() for f in sorted(bag.glob('*.mcap')))) \
        .hexdigest()


def test_fine_tuning_records_bags_init_and_errors_before_and_after(init_model, bags, tmp_path,
                                                                   capsys):
    init_dir = init_model
    a, b, c = bags
    out = tmp_path / 'new'
    code, printed, err = run(capsys, '--bags', a.parent, '--held-out', c, '--init', init_dir,
                             '--out', out, '--epochs', '1', '--test-trajectories', '40')
    assert code == 0, err
    assert err == ''
    meta = json.loads((out / 'model.json').read_text())
    info = meta['retrain']
    assert [bag['path'] for bag in info['bags']] == [str(a), str(b)]      # the directory's
    for entry, bag in zip(info['bags'], (a, b)):
        assert entry['sha256'] == sha256_of(bag)
        assert entry['files'][0]['sha256'] == hashlib.sha256(
            (bag / f'{bag.name}_0.mcap').read_bytes()).hexdigest()
    assert info['bags'][0]['messages'] == {'/tsr/excitation': 160, '/tsr/run_info': 2,
                                           '/tsr/state': 160, '/tsr/tension_cmd': 160}
    # 160 and 130 states: 159 and 129 transitions; a 30-step window starts every 3 steps
    # (the default stride): starts 0..129 and 0..99, but the first bag gives up its first
    # 90-step block (3 windows) for validation, so its training windows start at 90..129. The
    # second bag's blocks are not due (every 10th block from block 1). Held-out windows never
    # overlap: 99 // 30.
    assert [bag['windows'] for bag in info['bags']] == [14, 34]
    assert info['validation_windows'] == 3
    assert info['stride'] == 3
    assert info['recorded_windows'] == 48 and meta['data']['train_trajectories'] == 48
    assert info['held_out'][0]['sha256'] == sha256_of(c) and info['held_out'][0]['windows'] == 3
    weights = (init_dir / 'weights.safetensors').read_bytes()
    assert info['init'] == {'given': str(init_dir), 'path': str(init_dir.resolve()),
                            'fine_tuned': True,
                            'weights_sha256': hashlib.sha256(weights).hexdigest()}
    for when in ('errors_before', 'errors_after'):
        assert info[when]['held_out']['windows'] == 3
        assert info[when]['table1']['windows'] > 30
        assert np.isfinite(info[when]['held_out']['summed_mse'])
    assert meta['metrics']['test']['summed_mse'] == info['errors_after']['held_out'][
        'summed_mse']
    assert info['command'].startswith('retrain --bags ') and '--held-out' in info['command']
    git = info['git_commit']
    assert git == 'unknown' or (len(git) == 40 and int(git, 16) >= 0)
    # Fine-tuning kept the init's architecture and normalisation.
    assert meta['config']['lift_dim'] == 4 and meta['training']['epochs'] == 1
    init_meta = json.loads((init_dir / 'model.json').read_text())
    assert meta['training']['learning_rate'] == pytest.approx(
        init_meta['training']['learning_rate'] * retraining.FINE_TUNE_LEARNING_RATE_FACTOR)
    new, old = LiftedModel.load(out), LiftedModel.load(init_dir)
    np.testing.assert_array_equal(new.mean, old.mean)
    np.testing.assert_array_equal(new.std, old.std)
    # The supervisor's envelope: the init's (the bags' states near x = 0 lie inside it) with
    # the states of the 48 recorded 30-step windows counted in.
    assert meta['envelope']['states'] == init_meta['envelope']['states'] + 48 * 31
    for side in (0, 1):
        np.testing.assert_array_equal(new.envelope[side], old.envelope[side])
    assert 'held_out 30-step summed MSE before (3 windows)' in printed
    assert 'held_out 30-step summed MSE, before -> after' in printed
    assert f'new  {out}: mean' in printed


def test_retraining_on_the_loop_s_bags_lowers_the_held_out_error(init_model, bags, tmp_path,
                                                                 capsys):
    """What retraining is for: the init model (fitted on sampled Table-1 data) fine-tuned on
    the loop's own bags predicts a held-out bag of the same loop better, measured on that
    bag's windows alone (no sampled test set mixed in)."""
    a, b, c = bags
    out = tmp_path / 'tuned'
    code, printed, err = run(capsys, '--bags', a.parent, '--held-out', c, '--init', init_model,
                             '--out', out, '--epochs', '20', '--test-trajectories', '0')
    assert code == 0, err
    info = json.loads((out / 'model.json').read_text())['retrain']
    before = info['errors_before']['held_out']['summed_mse']
    after = info['errors_after']['held_out']['summed_mse']
    assert after < 0.5 * before, (before, after)


def test_retrain_on_bags_stock_rosbag2_wrote(tmp_path, capsys):
    """`ros2 bag record` bags (tests/bag/rosbag2_style.py: rosbag2 0.26's layout and schema
    spelling) train and score like the project's own."""
    train, held = (stock_bag(tmp_path / name, n, seed)[0]
                   for name, n, seed in (('train', 130, 1), ('held', 100, 2)))
    code, printed, err = run(capsys, '--bags', train, '--held-out', held, '--out',
                             tmp_path / 'm', '--config-json', json.dumps({**TINY, 'epochs': 1}),
                             '--test-trajectories', '0')
    assert code == 0, err
    info = json.loads((tmp_path / 'm' / 'model.json').read_text())['retrain']
    assert info['bags'][0]['messages']['/tsr/state'] == 130 and info['bags'][0]['windows'] > 0
    assert info['errors_after']['held_out']['windows'] == 3


def test_a_bag_both_trained_on_and_held_out_is_refused(bags, tmp_path, capsys):
    a, b, _ = bags
    code, _, err = run(capsys, '--bags', a.parent, '--held-out', a, '--out', tmp_path / 'm',
                       '--config-json', json.dumps(TINY))
    assert code == 2 and err.count('\n') == 1
    assert err.startswith(f'retrain: {a}: given to train on and held out')
    copy = shutil.copytree(b, tmp_path / 'copy_of_b')        # same data under another name
    code, _, err = run(capsys, '--bags', a.parent, '--held-out', copy, '--out', tmp_path / 'm',
                       '--config-json', json.dumps(TINY))
    assert code == 2 and err.count('\n') == 1
    assert err.startswith(f'retrain: {b} has the same content as the held-out bag {copy}')
    # A `bag recover` copy: the same messages in other files (recover writes 1 MiB chunks, this
    # bag has small ones), refused all the same.
    small = plant_bag(tmp_path / 'small_chunks', 100, 4, chunk_size=2000)
    recovered = tmp_path / 'recovered'
    bag_tool.recover(small, out=recovered)
    assert sha256_of(recovered) != sha256_of(small)
    code, _, err = run(capsys, '--bags', a, small, '--held-out', recovered, '--out',
                       tmp_path / 'm', '--config-json', json.dumps(TINY))
    assert code == 2 and err == (f'retrain: {small} has the same content as the held-out bag '
                                 f'{recovered}: a bag is trained on or held out, not both\n')
    assert not (tmp_path / 'm').exists()
    # Held out twice under two names: its windows would count twice in the scores.
    code, _, err = run(capsys, '--bags', a, '--held-out', small, recovered, '--out',
                       tmp_path / 'm', '--config-json', json.dumps(TINY))
    assert code == 2 and err.splitlines() == [
        f'retrain: {recovered}: same messages (sha256 {err.split("sha256 ")[1][:12]}) as '
        f'{small}, given twice', 'retrain: 1 bad bags (--skip-bad skips them)']
    assert not (tmp_path / 'm').exists()


def test_bad_bags_are_named_and_exit_2_or_skipped(bags, tmp_path, capsys):
    a = bags[0]
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'empty' / 'empty_0.mcap').write_bytes(b'')
    x = np.zeros((20, 4))
    short = write_loop(tmp_path / 'short', x, np.full(20, 3.0))
    args = ['--bags', a, tmp_path / 'empty', short, '--out', tmp_path / 'm', '--config-json',
            json.dumps({**TINY, 'epochs': 1}), '--test-trajectories', '40']
    code, _, err = run(capsys, *args)
    assert code == 2 and not (tmp_path / 'm').exists()
    assert err.splitlines() == [
        f'retrain: {tmp_path / "empty"}: empty bag: no readable message (empty_0.mcap: empty '
        '(0 bytes))',
        f'retrain: {short}: no complete 30-step window: 20 states, longest gap-free run 19 '
        'steps',
        'retrain: 2 bad bags (--skip-bad skips them)']
    code, printed, err = run(capsys, *args, '--skip-bad')
    assert code == 0
    assert f'retrain: warning: skipped training bag: {tmp_path / "empty"}: empty bag' in err
    assert 'no --held-out bags' in err
    skipped = json.loads((tmp_path / 'm' / 'model.json').read_text())['retrain']['skipped']
    assert [s['bag'] for s in skipped] == [str(tmp_path / 'empty'), str(short)]


def test_skipping_every_held_out_bag_with_no_table1_test_is_one_line(bags, tmp_path, capsys):
    """Nothing left to score the models on: refused before training, not a traceback after."""
    a = bags[0]
    (tmp_path / 'failed').mkdir()                      # what a deploy that failed leaves
    (tmp_path / 'failed' / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    code, printed, err = run(capsys, '--bags', a, '--held-out', tmp_path / 'failed', '--out',
                             tmp_path / 'm', '--config-json', json.dumps({**TINY, 'epochs': 1}),
                             '--test-trajectories', '0', '--skip-bad')
    assert code == 2 and not (tmp_path / 'm').exists()
    assert err.splitlines() == [
        f'retrain: warning: skipped held-out bag: {tmp_path / "failed"}: empty bag: no .mcap '
        'files',
        'retrain: no usable held-out bag and --test-trajectories 0: nothing to test on (give a '
        'usable --held-out bag or --test-trajectories > 0)']
    assert 'training on' not in printed


def test_from_scratch_with_a_config_and_a_sampled_mix(bags, init_model, tmp_path, capsys):
    a, b, c = bags
    # --stride 30: non-overlapping windows, 2 + 4 of them (the first bag's first three are
    # its validation block).
    code, _, err = run(capsys, '--bags', a, b, '--held-out', c, '--out', tmp_path / 'm',
                       '--config-json', json.dumps({**TINY, 'epochs': 1}), '--stride', '30',
                       '--sampled-ratio', '2', '--test-trajectories', '0')
    assert code == 0, err
    meta = json.loads((tmp_path / 'm' / 'model.json').read_text())
    assert {k: {**meta['config'], **meta['training']}[k] for k in TINY} == TINY
    info = meta['retrain']
    assert info['init'] is None and info['errors_before'] == {'held_out': None}
    assert info['sampled_ratio'] == 2.0 and 0 < info['sampled_trajectories'] <= 12
    sampled = [p for p in meta['data']['train'] if p['source'] == 'sampled']
    assert len(sampled) == 1 and sampled[0]['ratio'] == 2.0 and sampled[0]['trajectories'] == 12
    assert meta['data']['train_trajectories'] == 6 + info['sampled_trajectories']
    # From scratch the envelope is the training states' own: recorded and sampled windows.
    training_states = meta['data']['train_trajectories'] * 31
    assert meta['envelope']['states'] == training_states
    # Fine-tuning cannot change the network; --from-scratch can.
    code, _, err = run(capsys, '--bags', a, '--init', init_model, '--out', tmp_path / 'n',
                       '--config-json', '{"lift_dim": 6}')
    assert code == 2 and err == ('retrain: cannot fine-tune with another lift_dim than the init '
                                 'model: use --from-scratch\n')


def test_an_unknown_config_field_is_named_with_the_known_ones(bags, init_model, tmp_path,
                                                              capsys):
    a = bags[0]
    known = ', '.join(sorted(model_file.KoopmanConfig.names()))
    for init in (['--init', init_model], []):          # fine-tuning and from scratch
        code, _, err = run(capsys, '--bags', a, *init, '--out', tmp_path / 'm',
                           '--config-json', '{"nosuchfield": 1, "epochs": 1}')
        assert code == 2 and err == ('retrain: --config-json: unknown field nosuchfield '
                                     f'(known: {known})\n')
        assert 'lift_dim' in known and 'epochs' in known
    assert not (tmp_path / 'm').exists()


def _retrain_rank(rank, port, argv, directory):
    """One torchrun rank: its environment, one thread, its own output files."""
    os.environ.update({'RANK': str(rank), 'LOCAL_RANK': str(rank), 'WORLD_SIZE': '2',
                       'MASTER_ADDR': '127.0.0.1', 'MASTER_PORT': str(port)})
    torch.set_num_threads(1)
    with open(directory / f'rank{rank}.out', 'w') as out, \
            open(directory / f'rank{rank}.err', 'w') as err:
        sys.stdout, sys.stderr = out, err
        code = retrain.main(argv)
    (directory / f'rank{rank}.code').write_text(str(code))


def test_retrain_under_two_ranks_shares_out_the_bags_and_rank_0_writes(bags, tmp_path):
    """The command as torchrun runs it: forked ranks with torchrun's environment."""
    import torch._dynamo  # noqa: F401  (DDP imports it: once here, not in each rank)
    a, b, c = bags
    out = tmp_path / 'm'
    argv = ['--bags', str(a), str(b), '--held-out', str(c), '--out', str(out), '--config-json',
            json.dumps({**TINY, 'epochs': 1}), '--test-trajectories', '0']
    context = multiprocessing.start_processes(
        _retrain_rank, args=(free_port(), argv, tmp_path), nprocs=2, join=False,
        start_method='fork')
    deadline = time.monotonic() + 120
    while not context.join(timeout=1.0):
        assert time.monotonic() < deadline, 'ranks did not finish'
    assert [(tmp_path / f'rank{r}.code').read_text() for r in (0, 1)] == ['0', '0']
    assert (tmp_path / 'rank1.out').read_text() == (tmp_path / 'rank1.err').read_text() == ''
    printed = (tmp_path / 'rank0.out').read_text()
    assert 'training on 48 recorded windows from 2 bags, 2 ranks sharing out bags' in printed
    # Rank 1's bag has no validation block: every rank falls back to the random split.
    assert 'a random split of the training windows' in printed
    info = json.loads((out / 'model.json').read_text())['retrain']
    assert (info['world_size'], info['sharding'], info['per_rank_batch']) == (2, 'bags', 16)
    assert [bag['sha256'] for bag in info['bags']] == [sha256_of(a), sha256_of(b)]
    assert info['errors_after']['held_out']['windows'] == 3


def test_anchor_from_data_is_the_mean_command_inside_the_zone():
    from tsr_koopman_ctrl.model import model_file
    bags = [{'steps': 120, 'sum': 120 * 3.30}, {'steps': 80, 'sum': 80 * 3.35}]
    config, record = retraining.anchored(model_file.KoopmanConfig(), 'data', bags)
    assert record['samples'] == 200
    assert config.model.anchor_tension == pytest.approx((120 * 3.30 + 80 * 3.35) / 200, abs=1e-12)
    few = [{'steps': 99, 'sum': 99 * 3.3}]               # fewer than 100 in-zone steps: kept
    default = model_file.KoopmanConfig()
    assert retraining.anchored(default, 'data', few)[0].model.anchor_tension == 3.0
    assert retraining.anchored(default, 3.2, few)[0].model.anchor_tension == 3.2
    with pytest.raises(retraining.UsageError, match='anchor'):
        retraining.anchored(model_file.KoopmanConfig(), 7.0, few)
    with pytest.raises(retraining.UsageError, match='--anchor'):
        retraining.parse_anchor('zero')


def test_fine_tuning_a_block_model_keeps_its_structure(bags, tmp_path, capsys):
    """retrain --init koopman_block must not turn its stable observable block into a dense A."""
    a, b, c = bags
    out = tmp_path / 'block'
    code, _, err = run(capsys, '--bags', a, b, '--held-out', c, '--init', 'koopman_block',
                       '--out', out, '--epochs', '1', '--test-trajectories', '0')
    assert code == 0, err
    meta = json.loads((out / 'model.json').read_text())
    assert meta['structure']['kind'] == 'block'
    from tsr_koopman_ctrl.model import LiftedModel
    # Stored in the usual basis, where A is not triangular; but only the state block's (at most
    # 4) eigenvalues may lie on or outside the unit circle.
    eigenvalues = np.abs(np.linalg.eigvals(LiftedModel.load(str(out)).A))
    assert np.count_nonzero(eigenvalues >= 1.0) <= 4


def test_a_fine_tune_may_change_the_training_but_not_the_model(init_model, tmp_path):
    """Every TrainingConfig field may change in a fine-tune (weight_physical too); a
    ModelConfig field that differs from the init's is refused."""
    options = retraining.RetrainOptions(init=str(init_model), config={'weight_physical': 0.5,
                                                                      'gamma': 0.99})
    config, init, _, init_model_config, _, _ = retraining.configure(options, tmp_path / 'm')
    assert config.training.weight_physical == 0.5 and config.training.gamma == 0.99
    assert config.model == init_model_config and init['fine_tuned']
    with pytest.raises(retraining.UsageError, match='another momentum_power .* --from-scratch'):
        retraining.configure(retraining.RetrainOptions(init=str(init_model),
                                                       config={'momentum_power': 1.0}),
                             tmp_path / 'm')
    with pytest.raises(retraining.UsageError, match='another anchor_tension .* use --anchor$'):
        retraining.configure(retraining.RetrainOptions(init=str(init_model),
                                                       config={'anchor_tension': 3.3}),
                             tmp_path / 'm')
