"""The model file and the lifted model in numpy: inversion, damage, the shipped models."""

import dataclasses

import numpy as np
import pytest

from conftest import step_differences

from tsr_koopman_ctrl.learning import dataset as datasets
from tsr_koopman_ctrl.learning import errors
from tsr_koopman_ctrl.model import lifted, model_file


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
    ('nan', 'A has non-finite'), ('no_dir', 'no such model directory'),
    ('nan_period', 'h (the sample period in tau) must be > 0')])
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
    elif damage == 'nan_period':
        import json
        meta_path = target / model_file.META_FILE
        meta = json.loads(meta_path.read_text())
        meta['config']['h'] = float('nan')
        meta_path.write_text(json.dumps(meta))
    elif damage == 'no_dir':
        target = tmp_path / 'nothing'
    with pytest.raises(model_file.ModelFileError) as error:
        lifted.LiftedModel.load(target)
    assert message in str(error.value) and str(target) in str(error.value)
    assert '\n' not in str(error.value)


def test_the_model_file_keeps_the_model_apart_from_its_training(tiny_model, tmp_path):
    """`config` holds what the model is and `training` how it was trained; a file in the flat
    layout (both in `config`) reads the same, and load gives one layout either way."""
    import json
    tensors, config, meta = model_file.load(tiny_model[0])
    written = json.loads((tiny_model[0] / model_file.META_FILE).read_text())
    assert set(written['config']) == set(model_file.ModelConfig.__dataclass_fields__)
    assert set(written['training']) == set(model_file.TrainingConfig.__dataclass_fields__)
    assert not set(written['config']) & set(written['training'])
    assert written['training']['epochs'] == 4 and written['config']['lift_dim'] == 4
    assert isinstance(config, model_file.ModelConfig) and not hasattr(config, 'epochs')
    flat = dict(written, config={**written['config'], **written['training'],
                                 'scale_free_lifted_loss': False})   # retired, off
    del flat['training']
    path = tmp_path / 'flat'
    model_file.save(path, tensors, config, {})
    (path / model_file.META_FILE).write_text(json.dumps(flat))
    _, config_flat, meta_flat = model_file.load(path)
    assert config_flat == config and meta_flat['training'] == meta['training']
    assert meta_flat['config'] == meta['config'] == dataclasses.asdict(config)
    recipe = model_file.KoopmanConfig.of(config_flat, meta_flat)
    assert recipe.training.learning_rate == 3e-3 and recipe.model.hidden == 16
    with pytest.raises(ValueError, match='nosuchfield'):
        recipe.replace(nosuchfield=1)


@pytest.mark.parametrize('config, training, read', [
    ({'lift_dim': 4, 'epochs': 9}, {'learning_rate': 0.5}, {'epochs': 9, 'learning_rate': 0.5}),
    ({'lift_dim': 4, 'epochs': 9}, {'epochs': 9}, {'epochs': 9}),
    ({'lift_dim': 4, 'epochs': 9}, {'epochs': 3}, "give ['epochs'] two values"),
    ({'lift_dim': 4}, {'momentum_power': 1.0}, "training keys ['momentum_power'] are no"),
    ({'lift_dim': 4}, {'scale_free_lifted_loss': False}, {}),
])
def test_a_model_file_s_training_fields_come_from_wherever_it_gives_them(config, training,
                                                                         read):
    """Training fields split between `config` and `training` are all read; a field given
    twice with two values, or a model field in `training` (which would change the model
    unseen: no tensor shape depends on momentum_power), is refused."""
    if isinstance(read, str):
        with pytest.raises(ValueError) as error:
            model_file.split_config(config, training)
        assert read in str(error.value)
        return
    model, fields = model_file.split_config(config, training)
    assert model == model_file.ModelConfig(lift_dim=4)
    assert fields == {**dataclasses.asdict(model_file.TrainingConfig()), **read}


@pytest.mark.parametrize('name', ['koopman_default', 'koopman_paper', 'koopman_block',
                                  'koopman_block_fast', 'koopman_retrieval', 'koopman_momentum'])
def test_shipped_model_error_on_fresh_data_stays_under_its_record(name):
    model = lifted.LiftedModel.load(name)
    recorded = model.metadata['metrics']['test']['summed_mse']
    fresh, _ = datasets.sample(datasets.SamplingConfig(trajectories=2000, seed=424242))
    result = errors.multistep_errors(model.predict(fresh.x[:, 0], fresh.u), fresh.x)
    # 2000 fresh trajectories against the 5000 of the record: allow sampling noise of 25%.
    assert result['summed_mse'] < 1.25 * recorded
    assert model.metadata['config']['lift_dim'] == 36


def test_koopman_retrieval_predicts_the_reeling_in_that_koopman_default_never_saw():
    """Fresh trajectories from the retrieval box (l' < 0), on the dynamics module: the relifted
    one-step map (what koopman_nmpc plans with) of koopman_retrieval, trained on such data, is
    far closer than koopman_default's, and its Table-1 error stays near the default's."""
    fresh, _ = datasets.sample(datasets.SamplingConfig(
        trajectories=500, seed=515151, state_low=datasets.RETRIEVAL_BOX_LOW,
        state_high=datasets.RETRIEVAL_BOX_HIGH))
    x, u = fresh.x[:, :-1].reshape(-1, 4), fresh.u.reshape(-1)
    models = {name: lifted.LiftedModel.load(name)
              for name in ('koopman_default', 'koopman_retrieval')}
    step_error = {name: np.mean((model.step(x, u) - fresh.x[:, 1:].reshape(-1, 4)) ** 2)
                  for name, model in models.items()}
    assert step_error['koopman_retrieval'] < 0.2 * step_error['koopman_default']
    test_error = {name: model.metadata['metrics']['test']['summed_mse']
                  for name, model in models.items()}
    assert test_error['koopman_retrieval'] < 1.25 * test_error['koopman_default']


def test_koopman_momentum_is_three_times_closer_where_the_tether_is_short():
    """Fresh Table-1 trajectories: the model on the scaled momentum against the main job's and
    the default model, over the windows whose tether dips below l = 0.1 and over all (on the
    5 000 test trajectories: 0.0996 against 0.405 and 0.394; 0.0142 against 0.0522, 0.0454)."""
    fresh, _ = datasets.sample(datasets.SamplingConfig(trajectories=2000, seed=424242))
    results = {}
    for name in ('koopman_momentum', 'koopman_retrieval', 'koopman_default'):
        model = lifted.LiftedModel.load(name)
        results[name] = errors.multistep_errors(model.predict(fresh.x[:, 0], fresh.u), fresh.x)
    assert lifted.LiftedModel.load('koopman_momentum').power == 1.0
    short = {name: r['short_tether']['summed_mse'] for name, r in results.items()}
    overall = {name: r['summed_mse'] for name, r in results.items()}
    assert results['koopman_momentum']['short_tether']['fraction'] > 0.05
    for other in ('koopman_retrieval', 'koopman_default'):
        assert short['koopman_momentum'] * 3 <= short[other], short
        assert overall['koopman_momentum'] * 2 <= overall[other], overall


def test_a_model_anchored_at_another_tension_holds_its_equilibrium_there(tiny_model):
    """The torch model and the controller's numpy model agree on an anchor other than 3: the
    lifted equilibrium drifts nowhere at (x = 0, u = anchor) in both."""
    import torch
    from tsr_koopman_ctrl.learning.deep_koopman import DeepKoopman
    from tsr_koopman_ctrl.model.lifted import LiftedModel
    from tsr_koopman_ctrl.model.model_file import load
    tensors, config, _ = load(tiny_model[0])
    config = dataclasses.replace(config, anchor_equilibrium=True, anchor_tension=3.3)
    lifted = LiftedModel(tensors, config)
    net = DeepKoopman.from_numpy(tensors, config).double().eval()
    origin = np.zeros(4)
    z_ref, u_hat_ref = lifted.reference()
    assert u_hat_ref == pytest.approx(0.0, abs=1e-12)
    assert lifted.tension_from_input(origin, u_hat_ref) == pytest.approx(3.3, abs=1e-9)
    with torch.no_grad():
        # (the torch model builds its anchor constant in float32)
        assert float(net.psi_uu(torch.tensor([3.3], dtype=torch.float64))) == pytest.approx(
            0.0, abs=1e-6)
        for u in (0.5, 3.0, 4.5):
            assert float(net.psi_u(torch.zeros(1, 4, dtype=torch.float64),
                                   torch.tensor([u], dtype=torch.float64))) == pytest.approx(
                float(lifted.psi_u(origin, u)), abs=1e-6)
    with pytest.raises(ValueError, match='anchor_tension'):
        dataclasses.replace(config, anchor_tension=6.0)


def test_a_relifted_prediction_is_the_one_step_map_iterated(tiny_model):
    model = lifted.LiftedModel.load(tiny_model[0])
    rng = np.random.default_rng(3)
    x0, u = rng.normal(scale=0.2, size=(2, 4)), rng.uniform(0.0, 5.0, size=(2, 6))
    got = model.predict(x0, u, relift=True)
    for i in range(2):     # an independent loop: x+ = C (A psi_x(x) + B psi_ux(x) psi_uu(u))
        x = x0[i]
        for k in range(6):
            z = model.A @ model.psi_x(x) + model.B[:, 0] * float(
                model.psi_ux(x) * model.input_map(u[i, k]))
            x = model.C @ z
            np.testing.assert_allclose(got[i, k + 1], x, rtol=1e-10, atol=1e-12)
    # One step is the same either way; later steps are not.
    linear = model.predict(x0, u)
    np.testing.assert_allclose(linear[:, 1], got[:, 1], rtol=1e-12)
    assert not np.allclose(linear[:, 2:], got[:, 2:])


def test_predict_takes_one_start_as_1d_and_names_the_shapes_it_wants(tiny_model):
    model = lifted.LiftedModel.load(tiny_model[0])
    x0, u = np.array([0.1, 0.0, -0.5, 0.2]), np.linspace(2.0, 4.0, 5)
    np.testing.assert_array_equal(model.predict(x0, u), model.predict(x0[None], u[None]))
    for bad_x0, bad_u in ((np.zeros((2, 4)), u), (np.zeros((1, 3)), u[None])):
        with pytest.raises(ValueError, match=r'predict takes x0 \(N, 4\) and u \(N, T\), got'):
            model.predict(bad_x0, bad_u)


@pytest.mark.parametrize('activation', ['tanh', 'elu'])
def test_the_analytic_step_jacobians_match_central_differences(tiny_model, activation):
    """step_jacobians (forward mode through the networks) against central differences of
    `step` itself, for either activation (the tiny model's weights read as either)."""
    tensors, config, _ = model_file.load(tiny_model[0])
    model = lifted.LiftedModel(tensors, dataclasses.replace(config, activation=activation))
    rng = np.random.default_rng(5)
    x, u = rng.normal(scale=[0.3, 0.3, 0.3, 0.5], size=(6, 4)), rng.uniform(0.0, 5.0, 6)
    following, d_state, d_tension = model.step_jacobians(x, u)
    np.testing.assert_allclose(following, model.step(x, u), rtol=1e-12, atol=1e-14)
    by_state, by_tension = step_differences(model, x, u)
    np.testing.assert_allclose(d_state, by_state, atol=1e-8)
    np.testing.assert_allclose(d_tension, by_tension, atol=1e-8)
    assert np.abs(d_state - np.eye(4)).max() > 1e-3     # not the identity the map is close to
    assert np.abs(d_tension).max() > 1e-3


@pytest.mark.parametrize('activation', ['tanh', 'elu'])
def test_the_exact_lift_jacobian_matches_central_differences(tiny_model, activation):
    tensors, config, _ = model_file.load(tiny_model[0])
    model = lifted.LiftedModel(tensors, dataclasses.replace(config, activation=activation))
    eps = 1e-6
    for x in (np.array([0.0, 0.0, 0.0, 0.0]), np.array([0.3, -0.2, -0.5, 0.4])):
        by_differences = np.stack([(model.psi_x(x + eps * e) - model.psi_x(x - eps * e))
                                   / (2 * eps) for e in np.eye(4)], axis=1)
        jacobian = model.lift_jacobian(x)
        np.testing.assert_allclose(jacobian, by_differences, atol=1e-8)
        np.testing.assert_array_equal(jacobian[:4], np.eye(4))     # psi_x starts with x
        assert np.abs(jacobian[4:]).max() > 1e-3


def test_relifting_keeps_the_shipped_model_accurate_over_a_whole_deployment():
    """Along a closed-loop deployment from the paper's start (the plant's own trajectory), the
    lifted linear system of koopman_default diverges within 100 steps (its A has modes up to
    1.11 per step); relifted every step it stays within 0.2 of the plant over 300."""
    from tsr_sim import dynamics
    from tsr_koopman_ctrl.control import closed_loop, make_controller
    model = lifted.LiftedModel.load('koopman_default')
    states, tensions = closed_loop(make_controller('linear_lqr'), dynamics.PAPER_INITIAL_STATE,
                                   300)
    linear = model.predict(states[:1], tensions[None])[0]
    relifted = model.predict(states[:1], tensions[None], relift=True)[0]
    assert np.abs(linear[100] - states[100]).max() > 10.0
    assert np.abs(relifted[1:] - states[1:]).max() < 0.2


def test_a_saved_model_is_readable_as_the_umask_allows(tiny_model, tmp_path):
    """safetensors created the weights 0600, so a model retrained by one user could not be
    deployed by another; both files now take the umask's mode, as model.json always did."""
    import os
    import stat
    tensors, config, metadata = model_file.load(tiny_model[0])
    previous = os.umask(0o022)
    try:
        model_file.save(tmp_path / 'saved', tensors, config, metadata)
    finally:
        os.umask(previous)
    for name in (model_file.WEIGHTS_FILE, model_file.META_FILE):
        assert stat.S_IMODE((tmp_path / 'saved' / name).stat().st_mode) == 0o644, name
