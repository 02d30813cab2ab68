"""A model that evolves the scaled momentum l^p (1 + theta') in place of theta'."""


import numpy as np
import pytest
import torch

from conftest import step_differences, tiny_config

from tsr_koopman_ctrl.control import make_controller
from tsr_koopman_ctrl.learning.trainer import save_model, Trainer
from tsr_koopman_ctrl.model import coordinates, LiftedModel

POWER = 0.75


def states(count=300, seed=0):
    """States over and beyond Table 1, tethers from below the floor to 1.5."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.5, 1.5, size=(count, 4))
    x[:, 2] = rng.uniform(-1.0 + 0.2 * coordinates.LENGTH_FLOOR, 0.5, count)
    return x


@pytest.mark.parametrize('power', [0.0, 0.75, 1.0, 2.0])
def test_the_round_trip_is_exact_in_numpy_and_torch(power):
    x = states()
    s = coordinates.to_model(x, power)
    # Exact to rounding, which the way back scales by 1 / L^p (1e4 at p = 2 on the floor).
    rounding = 1e-15 / coordinates.LENGTH_FLOOR ** power
    np.testing.assert_allclose(coordinates.to_state(s, power), x, rtol=0, atol=10 * rounding)
    tensor = torch.as_tensor(x)
    back = coordinates.to_state(coordinates.to_model(tensor, power), power)
    np.testing.assert_allclose(back.numpy(), x, rtol=0, atol=10 * rounding)
    np.testing.assert_allclose(coordinates.to_model(tensor, power).numpy(), s, rtol=1e-14)
    # theta, l and l' are the physical state's own; the equilibrium is s = 0.
    np.testing.assert_array_equal(s[:, [0, 2, 3]], x[:, [0, 2, 3]])
    assert not coordinates.to_model(np.zeros(4), power).any()


def test_the_scaled_momentum_is_the_one_from_the_equations():
    theta_rate, length = 0.4, 0.3
    x = np.array([0.1, theta_rate, length - 1.0, 0.2])
    assert coordinates.to_model(x, 1.0)[1] == pytest.approx(length * (1 + theta_rate) - 1)
    assert coordinates.to_model(x, 2.0)[1] == pytest.approx(length ** 2 * (1 + theta_rate) - 1)


@pytest.mark.parametrize('power', [0.75, 1.0])
def test_the_coordinate_jacobians_match_central_differences(power):
    x = states(seed=1)
    x = x[np.abs(1.0 + x[:, 2] - coordinates.LENGTH_FLOOR) > 1e-4]    # off the floor's kink
    eps = 1e-7

    def differences(function, at):
        return np.stack([(function(at + eps * e, power) - function(at - eps * e, power))
                         / (2 * eps) for e in np.eye(4)], axis=-1)

    np.testing.assert_allclose(coordinates.to_model_jacobian(x, power),
                               differences(coordinates.to_model, x), atol=1e-6)
    s = coordinates.to_model(x, power)
    np.testing.assert_allclose(coordinates.to_state_jacobian(s, power),
                               differences(coordinates.to_state, s), atol=1e-5)


def test_a_power_outside_its_range_is_refused_in_one_line():
    with pytest.raises(ValueError, match=r'momentum_power must be in \[0.0, 2.0\], got 3'):
        tiny_config().replace(momentum_power=3)


@pytest.fixture(scope='module')
def momentum_model(small_data, tmp_path_factory):
    """(directory, torch model) of a tiny model trained on the scaled momentum."""
    out = tmp_path_factory.mktemp('momentum')
    config = tiny_config().replace(momentum_power=POWER, weight_physical=1.0)
    trainer = Trainer(config, out, progress=False)
    net = trainer.fit(small_data)
    save_model(out, net, config, trainer, small_data, small_data, 1.0, 'test')
    return out, net, trainer


def test_training_on_the_momentum_learns_and_numpy_matches_torch(momentum_model, small_data):
    out, net, trainer = momentum_model
    val = [h['val_summed_mse'] for h in trainer.history]
    assert val[-1] < 0.8 * val[0], val
    assert all(h['physical'] > 0.0 for h in trainer.history)
    model = LiftedModel.load(out)
    assert model.power == POWER
    x0, u = small_data.x[:20, 0], small_data.u[:20]
    with torch.no_grad():
        expected = net.predict(torch.as_tensor(x0, dtype=torch.float32),
                               torch.as_tensor(u, dtype=torch.float32)).numpy()
    predicted = model.predict(x0, u)
    np.testing.assert_allclose(predicted, expected, atol=2e-4, rtol=1e-4)
    # Physical states come back: the first is the start itself, not its coordinates.
    np.testing.assert_allclose(predicted[:, 0], x0, atol=1e-12)
    # The lifted state starts with the model's state, and normalises it.
    s = coordinates.to_model(x0, POWER)
    np.testing.assert_allclose(model.psi_x(x0)[:, :4], s, atol=1e-12)
    np.testing.assert_allclose(model.mean, coordinates.to_model(
        small_data.x.reshape(-1, 4), POWER).mean(axis=0), rtol=0.1, atol=0.05)


def test_the_momentum_models_step_jacobians_match_central_differences(momentum_model):
    model = LiftedModel.load(momentum_model[0])
    rng = np.random.default_rng(5)
    x = rng.normal(scale=[0.3, 0.3, 0.3, 0.5], size=(6, 4))
    x[0, 2] = -0.9     # a short tether: l = 0.1
    u = rng.uniform(0.0, 5.0, 6)
    following, d_state, d_tension = model.step_jacobians(x, u)
    np.testing.assert_allclose(following, model.step(x, u), rtol=1e-12, atol=1e-13)
    by_state, by_tension = step_differences(model, x, u)
    np.testing.assert_allclose(d_state, by_state, atol=1e-7)
    np.testing.assert_allclose(d_tension, by_tension, atol=1e-7)
    # The lifting's Jacobian, and the local linear model (its state rows mapped back).
    eps = 1e-6
    at = np.array([0.3, -0.2, -0.5, 0.4])
    jacobian = model.lift_jacobian(at)
    np.testing.assert_allclose(jacobian, np.stack(
        [(model.psi_x(at + eps * e) - model.psi_x(at - eps * e)) / (2 * eps)
         for e in np.eye(4)], axis=1), atol=1e-7)
    # The local linear model: in the lifted input u_hat, held at its value at `at`.
    linear, b_x = model.local_linear_model(at)
    u_hat = float(model.psi_u(at, model.config.anchor_tension))

    def step(x, u_hat):
        following = model.psi_x(x) @ model.A[:4].T + u_hat * model.B[:4, 0]
        return coordinates.to_state(following, POWER)

    np.testing.assert_allclose(linear, np.stack(
        [(step(at + eps * e, u_hat) - step(at - eps * e, u_hat)) / (2 * eps)
         for e in np.eye(4)], axis=1), atol=1e-7)
    np.testing.assert_allclose(b_x[:, 0], (step(at, u_hat + eps) - step(at, u_hat - eps))
                               / (2 * eps), atol=1e-7)


def test_the_linear_laws_refuse_a_momentum_model_and_the_nmpc_flies_it(momentum_model):
    directory = str(momentum_model[0])
    for name in ('koopman_lqr', 'koopman_mpc'):
        with pytest.raises(ValueError, match=r"evolves the scaled momentum l\^0.75 .*fly it "
                                             'with koopman_nmpc'):
            make_controller(name, model=directory, supervisor='none', safety='none')
    law = make_controller('koopman_nmpc', model=directory, supervisor='none', safety='none')
    tension = law.compute(np.array([0.0, 0.0, -0.95, 1.0]))
    assert 0.0 <= tension <= 5.0
