"""The deep Koopman model and its training (torch)."""

import json

import numpy as np
import pytest
import torch
from tsr_sim import dynamics

from conftest import tiny_config

from tsr_koopman_ctrl.learning import deep_koopman
from tsr_koopman_ctrl.learning import trainer as training
from tsr_koopman_ctrl.model import lifted, model_file
from tsr_koopman_ctrl.commands import train


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
    first = training.Trainer(tiny_config().replace(epochs=2), tmp_path,
                             progress=False)
    first.fit(small_data)
    longer = training.Trainer(tiny_config().replace(epochs=3), tmp_path,
                              progress=False)
    longer.fit(small_data, resume=True)
    assert [h['epoch'] for h in longer.history] == [1, 2, 3]
    assert longer.history[:2] == first.history
    other = training.Trainer(tiny_config().replace(lift_dim=5), tmp_path,
                             progress=False)
    with pytest.raises(ValueError, match=r"different \['lift_dim'\]"):
        other.fit(small_data, resume=True)


def test_controllability_loss_and_rank():
    tol = model_file.TrainingConfig().controllability_tol
    a = torch.diag(torch.tensor([0.5, 0.7, 0.9]))
    good = deep_koopman.controllability_loss(a, torch.ones(3, 1), tol)
    bad = deep_koopman.controllability_loss(a, torch.tensor([[1.0], [1.0], [0.0]]), tol)
    assert good.item() < 0.01 and bad.item() > 0.3
    assert lifted.controllability_rank(a.numpy(), np.ones((3, 1))) == 3
    assert lifted.controllability_rank(a.numpy(), np.array([[1.0], [1.0], [0.0]])) == 2
    b = torch.tensor([[1.0], [1.0], [1e-3]], requires_grad=True)
    deep_koopman.controllability_loss(a, b, tol).backward()
    assert torch.isfinite(b.grad).all() and b.grad.abs().sum() > 0


def test_train_cli_rejects_bad_data_with_one_line(tmp_path, capsys):
    bad = tmp_path / 'x.npz'
    bad.write_text('not a dataset')
    assert train.main(['--out', str(tmp_path / 'm'), '--trajectories', '0',
                       '--data', str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('train: ') and 'x.npz' in err and '\n' not in err


def test_equilibrium_loss_pins_the_reference_as_a_fixed_point(small_data):
    drifts = []
    for weight in (0.0, 10.0):
        config = tiny_config().replace(weight_equilibrium=weight)
        net = training.Trainer(config, progress=False).fit(small_data)
        with torch.no_grad():
            drifts.append(deep_koopman.equilibrium_drift(net).item())
    assert drifts[1] < 0.2 * drifts[0], drifts


@pytest.fixture(scope='module')
def anchored_model(small_data):
    config = tiny_config().replace(anchor_equilibrium=True, weight_one_step=1.0, epochs=2)
    net = training.Trainer(config, progress=False).fit(small_data)
    return net, lifted.LiftedModel(net.to_numpy(), config.model)


def test_anchored_model_has_the_equilibrium_as_exact_fixed_point(anchored_model, small_data):
    net, numpy_model = anchored_model
    origin = np.zeros(4)
    np.testing.assert_allclose(numpy_model.psi_x(origin), 0.0, atol=1e-12)
    assert float(numpy_model.psi_u(origin, dynamics.EQUILIBRIUM_TENSION)) == pytest.approx(
        0.0, abs=1e-12)
    with torch.no_grad():
        assert deep_koopman.equilibrium_drift(net).item() < 1e-10
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
        loss = deep_koopman.one_step_error(net, net.psi_x(x), u).item()
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
        config = tiny_config().replace(weight_one_step=weight)
        net = training.Trainer(config, progress=False).fit(small_data)
        with torch.no_grad():
            errors_by_weight.append(deep_koopman.one_step_error(net, net.psi_x(x), u).item())
    assert errors_by_weight[1] < 0.5 * errors_by_weight[0], errors_by_weight


def test_to_numpy_is_a_snapshot_the_optimiser_cannot_change():
    """The trainer keeps its best epoch with to_numpy(); on the CPU .numpy() alone shares
    memory with the parameters, which Adam updates in place, so the "best" was the last."""
    net = deep_koopman.DeepKoopman(tiny_config().model)
    snapshot = net.to_numpy()
    before = snapshot['A'].copy()
    with torch.no_grad():
        net.A.add_(1.0)
    np.testing.assert_array_equal(snapshot['A'], before)


def test_the_returned_model_is_the_best_epoch(tiny_model, small_data):
    out, net, trainer = tiny_model
    config = tiny_config().training
    _, val = small_data.split(1.0 - config.validation_fraction, seed=config.seed)
    score = training.evaluate(net, val, trainer.device)
    assert score['summed_mse'] == pytest.approx(trainer.best['summed_mse'], rel=1e-6)
    assert trainer.best['summed_mse'] == min(h['val_summed_mse'] for h in trainer.history)


def test_resume_from_a_damaged_checkpoint_is_one_line(small_data, tmp_path, capsys):
    (tmp_path / training.CHECKPOINT).write_bytes(b'not a checkpoint')
    trainer = training.Trainer(tiny_config(), tmp_path, progress=False)
    with pytest.raises(ValueError, match='is damaged or not a checkpoint') as error:
        trainer.fit(small_data, resume=True)
    assert '\n' not in str(error.value)
