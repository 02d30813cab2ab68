"""The learning core, ROS-free: sampler, dataset file, model file, training, baselines."""

import dataclasses
import json
import pathlib

import numpy as np
import pytest
import torch
from tsr_sim import dynamics

from tsr_koopman_ctrl import baselines, errors, koopman_model, lifted, model_file, train
from tsr_koopman_ctrl import dataset as datasets

TINY = model_file.KoopmanConfig(lift_dim=4, hidden=16, layers=2, input_hidden=8, input_layers=1,
                                input_terms=3, epochs=4, batch_size=32, learning_rate=3e-3)


@pytest.fixture(scope='module')
def small_data():
    return datasets.sample(datasets.SamplingConfig(trajectories=400, seed=3))[0]


@pytest.fixture(scope='module')
def tiny_model(small_data, tmp_path_factory):
    out = tmp_path_factory.mktemp('model')
    trainer = train.Trainer(TINY, out, progress=False)
    net = trainer.fit(small_data)
    train.save_model(out, net, TINY, trainer, small_data, small_data, 1.0, 'test')
    return out, net, trainer


def test_sampler_follows_table1_and_drops_runaways():
    config = datasets.SamplingConfig(trajectories=3000, seed=7, substeps=1)
    data, dropped = datasets.sample(config)
    assert len(data) + dropped == 3000 and dropped > 0   # the paper's ranges do run away
    assert np.all(data.x[:, 0] >= dynamics.TABLE1_STATE_LOW)
    assert np.all(data.x[:, 0] <= dynamics.TABLE1_STATE_HIGH)
    assert data.u.min() >= 0.0 and data.u.max() <= 5.0 and data.u.shape[1] == 30
    assert np.all(np.abs(data.x) <= config.max_abs_state)
    # Every kept trajectory is the plant's own response to its tensions.
    check = dynamics.rollout(data.x[:50, 0], data.u[:50], config.h, config.substeps)
    np.testing.assert_allclose(check, data.x[:50], rtol=0, atol=1e-12)
    again, _ = datasets.sample(config)
    np.testing.assert_array_equal(again.x, data.x)
    assert data.provenance[0]['dropped'] == dropped and data.provenance[0]['seed'] == 7


def test_dataset_file_round_trip_and_errors(small_data, tmp_path):
    path = tmp_path / 'd.npz'
    datasets.save(small_data, path)
    loaded = datasets.load(path)
    np.testing.assert_array_equal(loaded.x, small_data.x)
    np.testing.assert_array_equal(loaded.u, small_data.u)
    assert loaded.provenance == small_data.provenance and loaded.h == small_data.h
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(ValueError, match='d.npz: not a readable dataset'):
        datasets.load(path)
    with pytest.raises(ValueError, match='no such dataset'):
        datasets.load(tmp_path / 'missing.npz')


def test_windows_from_a_recorded_loop_skip_gaps_and_missing_commands():
    steps = np.r_[np.arange(0, 70), np.arange(80, 150)]
    x = np.random.default_rng(0).normal(size=(len(steps), 4))
    u = np.full(len(steps), 3.0)
    u[100] = np.nan
    data = datasets.from_loop({'step': steps, 'x': x, 'u': u}, steps=30, source='b')
    # Windows start at 0, 30 (ok), 60 (gap 69->80), 90 (nan at index 100), 120 (too short).
    assert len(data) == 2
    np.testing.assert_array_equal(data.x[1], x[30:61])
    mixed = datasets.concatenate([data, datasets.sample(
        datasets.SamplingConfig(trajectories=10))[0]])
    assert len(mixed) >= 2 + 9 and [p['source'] for p in mixed.provenance] == ['b', 'sampled']


def test_training_lowers_loss_and_numpy_model_matches_torch(tiny_model, small_data):
    out, net, trainer = tiny_model
    val = [h['val_summed_mse'] for h in trainer.history]
    assert val[-1] < 0.8 * val[0], val
    numpy_model = lifted.LiftedModel.load(out)
    x0, u = small_data.x[:20, 0], small_data.u[:20]
    with torch.no_grad():
        expected = net.predict(torch.as_tensor(x0, dtype=torch.float32),
                               torch.as_tensor(u, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(numpy_model.predict(x0, u), expected, atol=2e-4, rtol=1e-4)
    meta = json.loads((out / 'model.json').read_text())
    assert meta['metrics']['controllability_rank'] == numpy_model.controllability_rank()
    assert meta['config']['lift_dim'] == 4 and meta['data']['train'][0]['seed'] == 3


def test_resume_continues_from_the_checkpoint(small_data, tmp_path):
    first = train.Trainer(dataclasses.replace(TINY, epochs=2), tmp_path,
                          progress=False)
    first.fit(small_data)
    longer = train.Trainer(dataclasses.replace(TINY, epochs=3), tmp_path,
                           progress=False)
    longer.fit(small_data, resume=True)
    assert [h['epoch'] for h in longer.history] == [1, 2, 3]
    assert longer.history[:2] == first.history
    other = train.Trainer(dataclasses.replace(TINY, lift_dim=5), tmp_path,
                          progress=False)
    with pytest.raises(ValueError, match=r"different \['lift_dim'\]"):
        other.fit(small_data, resume=True)


def test_monotone_input_map_inverts_everywhere(tiny_model):
    model = lifted.LiftedModel.load(tiny_model[0])
    for u in (-3.0, 0.0, 0.7, 3.0, 5.0, 11.0):
        value = float(model.input_map(u))
        assert model.input_map.inverse(value) == pytest.approx(u, abs=1e-6)
        round_trip = float(model.input_map(model.input_map.inverse(value)))
        assert round_trip == pytest.approx(value, abs=1e-11)
    x = np.array([0.1, -0.2, -0.5, 0.3])
    u_hat = float(model.psi_u(x, 2.5))
    assert model.tension_from_input(x, u_hat) == pytest.approx(2.5, abs=1e-6)
    assert model.psi_ux(np.random.default_rng(0).normal(size=(100, 4)) * 50).min() >= 0.05


@pytest.mark.parametrize('damage, message', [
    ('truncate', 'corrupt or truncated'), ('delete_weights', 'weights.safetensors: missing'),
    ('bad_json', 'not valid JSON'), ('wrong_shape', 'A has shape'),
    ('nan', 'A has non-finite'), ('no_dir', 'no such model directory')])
def test_bad_model_files_give_one_clear_line(tiny_model, tmp_path, damage, message):
    tensors, config, meta = model_file.load(tiny_model[0])
    target = tmp_path / 'm'
    extra = {k: v for k, v in meta.items() if k not in ('format', 'version', 'config')}
    model_file.save(target, tensors, config, extra)
    weights = target / model_file.WEIGHTS_FILE
    if damage == 'truncate':
        weights.write_bytes(weights.read_bytes()[:500])
    elif damage == 'delete_weights':
        weights.unlink()
    elif damage == 'bad_json':
        (target / model_file.META_FILE).write_text('{"format": ')
    elif damage in ('wrong_shape', 'nan'):
        from safetensors.numpy import save_file
        arrays = {k: np.array(v, dtype=np.float32) for k, v in tensors.items()}
        arrays['A'] = arrays['A'][:-1] if damage == 'wrong_shape' else arrays['A'] * np.nan
        save_file(arrays, str(weights))
    elif damage == 'no_dir':
        target = tmp_path / 'nothing'
    with pytest.raises(model_file.ModelFileError) as error:
        lifted.LiftedModel.load(target)
    assert message in str(error.value) and str(target) in str(error.value)
    assert '\n' not in str(error.value)


def test_controllability_loss_and_rank():
    config = model_file.KoopmanConfig()
    a = torch.diag(torch.tensor([0.5, 0.7, 0.9]))
    good = koopman_model.controllability_loss(a, torch.ones(3, 1), config)
    bad = koopman_model.controllability_loss(a, torch.tensor([[1.0], [1.0], [0.0]]), config)
    assert good.item() < 0.01 and bad.item() > 0.3
    assert lifted.controllability_rank(a.numpy(), np.ones((3, 1))) == 3
    assert lifted.controllability_rank(a.numpy(), np.array([[1.0], [1.0], [0.0]])) == 2
    b = torch.tensor([[1.0], [1.0], [1e-3]], requires_grad=True)
    koopman_model.controllability_loss(a, b, config).backward()
    assert torch.isfinite(b.grad).all() and b.grad.abs().sum() > 0


def linear_system_data(n_traj=200, steps=30, seed=0):
    """Trajectories of a known stable linear system: the baselines must recover it exactly."""
    rng = np.random.default_rng(seed)
    a = np.array([[0.99, 0.01, 0, 0], [-0.03, 0.99, 0, -0.02], [0, 0, 1.0, 0.01],
                  [0, 0.02, 0.03, 0.98]])
    b = np.array([0.0, 0.0, 0.0, -0.01])
    x = np.empty((n_traj, steps + 1, 4))
    x[:, 0] = rng.uniform(-1, 1, (n_traj, 4))
    u = rng.uniform(0, 5, (n_traj, steps))
    for k in range(steps):
        x[:, k + 1] = x[:, k] @ a.T + u[:, k:k + 1] * b
    return datasets.Dataset(x, u, 0.01, [{'source': 'linear test system'}])


@pytest.mark.parametrize('method', [baselines.Edmd(lift_dim=6), baselines.Sindy(degree=2)])
def test_baselines_recover_a_linear_system(method):
    train_set, test_set = linear_system_data(seed=0), linear_system_data(50, seed=1)
    method.fit(train_set)
    result = errors.multistep_errors(method.predict(test_set.x[:, 0], test_set.u), test_set.x)
    assert result['summed_mse'] < 1e-12


def test_multistep_errors_by_hand():
    truth = np.zeros((2, 3, 4))
    predicted = truth.copy()
    predicted[0, 1, 0] = 2.0    # squared 4, mean over 2 traj and 4 comps at step 1 -> 0.5
    predicted[1, 2, 3] = np.nan
    result = errors.multistep_errors(predicted, truth)
    assert result['mse_per_step'][:2] == [0.0, 0.5]
    assert result['summed_mse'] == np.inf
    assert result['summed_mse_per_component']['theta'] == 2.0


def test_edmd_stabilised_clips_the_spectrum():
    a = np.array([[1.2, 0.3], [0.0, 0.5]])
    clipped = baselines.clip_spectrum(a)
    assert sorted(np.abs(np.linalg.eigvals(clipped))) == pytest.approx([0.5, 1.0])


def test_train_cli_rejects_bad_data_with_one_line(tmp_path, capsys):
    bad = tmp_path / 'x.npz'
    bad.write_text('not a dataset')
    assert train.main(['--out', str(tmp_path / 'm'), '--trajectories', '0',
                       '--data', str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('train: ') and 'x.npz' in err and '\n' not in err


MODELS = pathlib.Path(__file__).resolve().parents[1] / 'models'


@pytest.mark.parametrize('name', ['koopman_default', 'koopman_paper'])
def test_shipped_model_error_on_fresh_data_stays_under_its_record(name):
    model = lifted.LiftedModel.load(MODELS / name)
    recorded = model.metadata['metrics']['test']['summed_mse']
    fresh, _ = datasets.sample(datasets.SamplingConfig(trajectories=2000, seed=424242))
    result = errors.multistep_errors(model.predict(fresh.x[:, 0], fresh.u), fresh.x)
    # 2000 fresh trajectories against the 5000 of the record: allow sampling noise of 25%.
    assert result['summed_mse'] < 1.25 * recorded
    assert model.metadata['config']['lift_dim'] == 36


def test_koopman_lqr_gain_stabilises_the_lifted_system(tiny_model):
    from tsr_koopman_ctrl import controllers
    controller = controllers.KoopmanLqr(lifted.LiftedModel.load(tiny_model[0]))
    assert controller.closed_loop_spectral_radius() < 1.0


def test_mpc_without_active_constraints_moves_like_the_lqr(tiny_model):
    """With the terminal cost from the DARE, unconstrained MPC is the LQR (Bellman)."""
    from tsr_koopman_ctrl import controllers
    model = lifted.LiftedModel.load(tiny_model[0])
    mpc = controllers.KoopmanMpc(model, horizon=10, r=15.0, state_weight='lifted',
                                 terminal='riccati', input_cost='level', u_max=1e6,
                                 theta_max=1e6)
    lqr = controllers.KoopmanLqr(model)
    mpc.drift = np.zeros_like(mpc.drift)   # the LQR assumes z_d is a fixed point
    for x in ([0.0, 0.0, 0.0, 0.0], [0.002, -0.001, 0.001, 0.0]):
        u_hat_lqr = lqr.u_hat_ref - float(lqr.gain @ (model.psi_x(np.array(x)) - lqr.z_ref))
        assert mpc.compute(x) == pytest.approx(model.tension_from_input(np.array(x), u_hat_lqr),
                                               abs=1e-4)
    assert mpc.fallbacks == 0


def test_mpc_respects_the_tension_bounds(tiny_model):
    from tsr_koopman_ctrl import controllers
    model = lifted.LiftedModel.load(tiny_model[0])
    mpc = controllers.KoopmanMpc(model, horizon=10, u_max=5.0)
    rng = np.random.default_rng(1)
    for x in rng.uniform(dynamics.TABLE1_STATE_LOW, dynamics.TABLE1_STATE_HIGH, (20, 4)):
        assert -1e-3 <= mpc.compute(x) <= 5.0 + 1e-3


def test_evaluate_command_writes_the_comparison(tiny_model, tmp_path):
    from tsr_koopman_ctrl import evaluate
    out = tmp_path / 'eval'
    assert evaluate.main(['--model', str(tiny_model[0]), '--out', str(out), '--no-sindy',
                          '--test-trajectories', '200']) == 0
    results = json.loads((out / 'comparison.json').read_text())
    assert set(results) == {'deep_koopman', 'edmd', 'edmd_stabilised'}
    # Re-sampled training data and the numpy model reproduce the deep model's own figure.
    model = lifted.LiftedModel.load(tiny_model[0])
    test, _ = datasets.sample(datasets.SamplingConfig(trajectories=200, seed=datasets.TEST_SEED))
    own = errors.multistep_errors(model.predict(test.x[:, 0], test.u), test.x)
    assert results['deep_koopman']['summed_mse'] == pytest.approx(own['summed_mse'])
    assert '| edmd_stabilised |' in (out / 'comparison.md').read_text()
    assert (out / 'error_vs_step.png').stat().st_size > 10_000


def test_equilibrium_loss_pins_the_reference_as_a_fixed_point(small_data):
    drifts = []
    for weight in (0.0, 10.0):
        config = dataclasses.replace(TINY, weight_equilibrium=weight)
        net = train.Trainer(config, progress=False).fit(small_data)
        with torch.no_grad():
            drifts.append(koopman_model.equilibrium_drift(net).item())
    assert drifts[1] < 0.2 * drifts[0], drifts


@pytest.fixture(scope='module')
def anchored_model(small_data):
    config = dataclasses.replace(TINY, anchor_equilibrium=True, weight_one_step=1.0, epochs=2)
    net = train.Trainer(config, progress=False).fit(small_data)
    return net, lifted.LiftedModel(net.to_numpy(), config)


def test_anchored_model_has_the_equilibrium_as_exact_fixed_point(anchored_model, small_data):
    net, numpy_model = anchored_model
    origin = np.zeros(4)
    np.testing.assert_allclose(numpy_model.psi_x(origin), 0.0, atol=1e-12)
    assert float(numpy_model.psi_u(origin, dynamics.EQUILIBRIUM_TENSION)) == pytest.approx(
        0.0, abs=1e-12)
    with torch.no_grad():
        assert koopman_model.equilibrium_drift(net).item() < 1e-10
        x0 = torch.as_tensor(small_data.x[:20, 0], dtype=torch.float32)
        expected = net.predict(x0, torch.as_tensor(small_data.u[:20], dtype=torch.float32))
    # The numpy model folds the anchor into its biases; both must predict the same.
    np.testing.assert_allclose(numpy_model.predict(small_data.x[:20, 0], small_data.u[:20]),
                               expected.numpy(), atol=2e-4, rtol=1e-4)


def test_one_step_error_is_relative_to_the_increment(anchored_model, small_data):
    net, numpy_model = anchored_model
    x = torch.as_tensor(small_data.x[:64], dtype=torch.float32)
    u = torch.as_tensor(small_data.u[:64], dtype=torch.float32)
    with torch.no_grad():
        loss = koopman_model.one_step_error(net, net.psi_x(x), x, u).item()
    # The same figure from the numpy model and numpy's own std of the increments.
    now, after = small_data.x[:64, :-1], small_data.x[:64, 1:]
    z = numpy_model.psi_x(now)
    predicted = (z @ numpy_model.A[:4].T
                 + numpy_model.psi_u(now, small_data.u[:64])[..., None] * numpy_model.B[:4].T)
    scale = (after - now).reshape(-1, 4).std(axis=0, ddof=1)
    assert loss == pytest.approx(np.mean(((predicted - after) / scale) ** 2), rel=1e-3)


def test_one_step_loss_lowers_the_one_step_error(small_data):
    errors_by_weight = []
    x = torch.as_tensor(small_data.x, dtype=torch.float32)
    u = torch.as_tensor(small_data.u, dtype=torch.float32)
    for weight in (0.0, 1.0):
        config = dataclasses.replace(TINY, weight_one_step=weight)
        net = train.Trainer(config, progress=False).fit(small_data)
        with torch.no_grad():
            errors_by_weight.append(koopman_model.one_step_error(net, net.psi_x(x), x, u).item())
    assert errors_by_weight[1] < 0.5 * errors_by_weight[0], errors_by_weight
