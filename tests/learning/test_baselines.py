"""EDMD, SINDy and the prediction error they and the deep model are judged by."""

import numpy as np
import pytest

from tsr_koopman_ctrl.learning import baselines, errors
from tsr_koopman_ctrl.learning import dataset as datasets


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
    truth = np.zeros((5, 3, 4))
    predicted = truth.copy()
    predicted[0, 1, 0] = 2.0      # squared 4: window sum 4 / 4 components = 1
    predicted[1, 2, 3] = np.nan   # diverged: not finite
    predicted[2, 2, 0] = 2e3      # diverged: beyond errors.DIVERGED
    result = errors.multistep_errors(predicted, truth)
    # Means over the three windows that did not diverge; the median over all five.
    assert result['mse_per_step'] == pytest.approx([0.0, 4.0 / 12.0, 0.0])
    assert result['summed_mse'] == pytest.approx(1.0 / 3.0)
    assert result['summed_mse_per_component']['theta'] == pytest.approx(4.0 / 3.0)
    assert result['summed_mse_median'] == pytest.approx(1.0)    # sorted: 0, 0, 1, inf, inf
    assert result['diverged_fraction'] == pytest.approx(0.4) and result['windows'] == 5
    everything_diverged = errors.multistep_errors(np.full((2, 3, 4), np.inf), np.zeros((2, 3, 4)))
    assert everything_diverged['summed_mse'] == np.inf
    assert everything_diverged['diverged_fraction'] == 1.0


def test_the_short_tether_windows_are_split_from_the_rest_by_hand():
    truth = np.zeros((4, 3, 4))
    truth[0, 2, 2] = -0.95          # l = 0.05 at the last step: a short-tether window
    truth[1, 1, 2] = -0.85          # l = 0.15: not one
    predicted = truth.copy()
    predicted[0, 1, 1] = 2.0        # window sum 4 / 4 = 1
    predicted[1, 1, 1] = 1.0        # window sum 0.25
    predicted[2, 1, 1] = np.inf     # diverged: in neither mean
    split = errors.multistep_errors(predicted, truth)['short_tether']
    assert split['fraction'] == pytest.approx(0.25)
    assert split['summed_mse'] == pytest.approx(1.0)
    assert split['rest_summed_mse'] == pytest.approx(0.25 / 2)     # windows 1 and 3
    assert split['share'] == pytest.approx(1.0 / 1.25)
    assert errors.multistep_errors(truth[1:], truth[1:])['short_tether']['summed_mse'] is None


def quadratic_system_data(x0, steps):
    """x+ = x + 0.1 x^2 per component (u has no effect): blows up from |x| > ~1 in a few tens
    of steps, and SINDy with quadratic terms recovers it exactly."""
    x = np.empty((len(x0), steps + 1, 4))
    x[:, 0] = x0
    with np.errstate(over='ignore'):
        for k in range(steps):
            x[:, k + 1] = x[:, k] + 0.1 * x[:, k] ** 2
    return datasets.Dataset(x, np.zeros((len(x0), steps)), 0.01, [{'source': 'quadratic'}])


def test_sindy_returns_a_diverging_prediction_instead_of_raising():
    rng = np.random.default_rng(0)
    train = quadratic_system_data(rng.uniform(-0.5, 0.5, (200, 4)), 5)
    sindy = baselines.Sindy(degree=2).fit(train)
    test = quadratic_system_data(np.r_[rng.uniform(-0.3, 0.3, (9, 4)), [[3.0, 0.0, 0.0, 0.0]]],
                                 30)
    with np.errstate(over='ignore'):
        predicted = sindy.predict(test.x[:, 0], test.u)
    assert predicted.shape == test.x.shape
    result = errors.multistep_errors(predicted, test.x)
    assert result['diverged_fraction'] == pytest.approx(0.1)    # the one from x = 3
    assert result['summed_mse'] < 1e-10                           # the other nine exact
    blown = predicted[-1, :, 0]
    assert np.nanmax(blown) > errors.DIVERGED and np.isnan(blown[-1])


def test_edmd_stabilised_clips_the_spectrum():
    a = np.array([[1.2, 0.3], [0.0, 0.5]])
    clipped = baselines.clip_spectrum(a)
    assert sorted(np.abs(np.linalg.eigvals(clipped))) == pytest.approx([0.5, 1.0])


@pytest.mark.parametrize('make', [lambda: baselines.Edmd(lift_dim=6),
                                  lambda: baselines.Sindy(degree=2)])
def test_bad_use_of_a_baseline_is_one_line(make):
    """Were AttributeErrors, a broadcast error or an IndexError."""
    data = linear_system_data(20)
    name = type(make()).__name__
    with pytest.raises(ValueError, match=f'{name}.predict before fit: call fit'):
        make().predict(data.x[:, 0], data.u)
    with pytest.raises(ValueError, match=rf'{name}.fit takes a Dataset .* got ndarray'):
        make().fit(data.x)
    model = make().fit(data)
    with pytest.raises(ValueError, match=r'predict takes x0 \(N, 4\) and u \(N, T\), got x0 '
                       r'\(20, 3\)'):
        model.predict(data.x[:, 0, :3], data.u)
    one = model.predict(data.x[0, 0], data.u[0])        # one start as 1-D, as LiftedModel's
    np.testing.assert_allclose(one[0], model.predict(data.x[:1, 0], data.u[:1])[0])


def test_edmd_needs_at_least_one_observable():
    with pytest.raises(ValueError, match='Edmd: lift_dim must be an integer >= 1, got 0'):
        baselines.Edmd(lift_dim=0)
