"""BlockKoopman: observables stable by construction, saved as an ordinary model file."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from conftest import tiny_config

from tsr_koopman_ctrl.learning import block_koopman, kinds
from tsr_koopman_ctrl.learning.trainer import save_model, Trainer
from tsr_koopman_ctrl.model import lifted, model_file
from tsr_koopman_ctrl.commands import train


def observable_block(net):
    """A_phi and the x -> Phi rows of A, in the training basis."""
    a = net.A.detach().double().numpy()
    n = net.config.state_dim
    return a[n:, n:], a[n:, :n]


@pytest.mark.parametrize('flat', [False, True], ids=['plain', 'flat'])
def test_short_block_training_stays_stable_and_saves_what_it_predicts(
        small_data, tmp_path, flat):
    config = tiny_config().replace(epochs=1)
    structure = block_koopman.BlockStructure(real_modes=2, radius=0.9, flat=flat)
    trainer = Trainer(config, tmp_path, progress=False, kind=kinds.Block(structure))
    net = trainer.fit(small_data.subset(np.arange(200)))
    assert isinstance(net, block_koopman.BlockKoopman) and trainer.history
    a_phi, coupling = observable_block(net)
    assert np.all(coupling == 0.0) and np.abs(np.linalg.eigvals(a_phi)).max() < 0.9
    assert np.all(net.B.detach().numpy()[config.model.state_dim:] == 0.0)

    save_model(tmp_path, net, config, trainer, small_data, small_data.subset(np.arange(20)),
               1.0, 'test')
    model = lifted.LiftedModel.load(tmp_path)
    a = net.A.detach().double().numpy()
    if flat:   # stored in the file's basis: z = T z_flat
        jacobian = net.anchor_jacobian().detach().double().numpy()
        t = block_koopman.flat_basis(jacobian, config.model.lifted_dim)
        a = t @ a @ np.linalg.inv(t)
    np.testing.assert_allclose(model.A, a, atol=1e-6)
    x0, u = small_data.x[:20, 0], small_data.u[:20]
    with torch.no_grad():
        expected = net.predict(torch.as_tensor(x0, dtype=torch.float32),
                               torch.as_tensor(u, dtype=torch.float32)).numpy()
    np.testing.assert_allclose(model.predict(x0, u), expected, atol=2e-4, rtol=1e-4)


def test_exported_a_is_the_materialised_one():
    config = tiny_config()
    structure = block_koopman.BlockStructure(real_modes=2, flat=False, observable_input=True)
    net = block_koopman.BlockKoopman(config.model, structure=structure)
    with torch.no_grad():
        net.top.normal_()
        net.real_raw.normal_()
    tensors = net.export_tensors()
    assert set(tensors) == set(model_file.expected_shapes(config.model))
    np.testing.assert_array_equal(tensors['A'], net.A.detach().double().numpy())
    tensors['A'][0, 0] += 1.0    # a copy, not a view of the parameters
    assert net.export_tensors()['A'][0, 0] != tensors['A'][0, 0]


def test_from_a_dense_model_pulls_its_observable_modes_inside(tiny_model):
    tensors, config, _ = model_file.load(tiny_model[0])
    tensors['A'][config.state_dim:, config.state_dim:] *= 2.0   # unstable observables
    structure = block_koopman.BlockStructure(radius=1.0, margin=0.95)
    net = block_koopman.from_tensors(tensors, config, structure)
    a_phi, coupling = observable_block(net)
    assert np.all(coupling == 0.0) and np.abs(np.linalg.eigvals(a_phi)).max() <= 0.95 + 1e-6
    odd = dataclasses.replace(structure, real_modes=3)
    with pytest.raises(ValueError, match='even'):
        block_koopman.BlockKoopman(config, structure=odd)


def test_train_cli_fine_tunes_a_block_model(tiny_model, tmp_path):
    out = tmp_path / 'block'
    assert train.main(['--out', str(out), '--init', str(tiny_model[0]), '--structure', 'block',
                       '--epochs', '1', '--trajectories', '100', '--test-trajectories', '20',
                       '--quiet']) == 0
    meta = json.loads((out / 'model.json').read_text())
    assert meta['structure']['kind'] == 'block' and meta['init'] == str(tiny_model[0])
    assert meta['config']['lift_dim'] == 4 and meta['training']['epochs'] == 1
    model = lifted.LiftedModel.load(out)
    values = np.linalg.eigvals(model.A)
    local = np.linalg.eigvals(model.local_linear_model()[0])
    assert all(np.min(np.abs(local - v)) < 1e-3 for v in values[np.abs(values) >= 1.0])


def test_a_block_model_fine_tuned_without_structure_stays_block(tiny_model, tmp_path):
    """The kind travels in the model file: `train --init` of a block model builds the block
    kind again, as `retrain` does; --structure dense turns it dense."""
    block = tmp_path / 'block'
    common = ['--epochs', '1', '--trajectories', '100', '--test-trajectories', '20', '--quiet']
    assert train.main(['--out', str(block), '--init', str(tiny_model[0]), '--structure',
                       'block', '--real-modes', '2', *common]) == 0
    record = json.loads((block / 'model.json').read_text())['structure']
    kind = kinds.from_metadata({'structure': record})
    assert kind == kinds.Block(block_koopman.BlockStructure(**{
        k: v for k, v in record.items() if k != 'kind'}))
    again = tmp_path / 'again'
    assert train.main(['--out', str(again), '--init', str(block), *common]) == 0
    assert json.loads((again / 'model.json').read_text())['structure']['kind'] == 'block'
    dense = tmp_path / 'dense'
    assert train.main(['--out', str(dense), '--init', str(block), '--structure', 'dense',
                       *common]) == 0
    assert 'structure' not in json.loads((dense / 'model.json').read_text())


def test_a_model_kind_from_metadata():
    assert kinds.from_metadata({}) == kinds.Dense()
    structure = block_koopman.BlockStructure(real_modes=4, radius=0.9)
    assert kinds.from_metadata({'structure': structure.to_dict()}) == kinds.Block(structure)
    with pytest.raises(ValueError, match="model kind 'sparse' is unknown"):
        kinds.from_metadata({'structure': {'kind': 'sparse'}})
    with pytest.raises(ValueError, match='bad structure record'):
        kinds.from_metadata({'structure': {'kind': 'block', 'colour': 'red'}})
