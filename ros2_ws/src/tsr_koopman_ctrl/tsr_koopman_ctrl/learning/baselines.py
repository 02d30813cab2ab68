"""The paper's comparison models, fit on the same trajectories as the deep Koopman model.

Both follow one interface (after pykoopman / pysindy): ``fit(dataset) -> self`` and
``predict(x0 (N, n), u (N, T)) -> states (N, T + 1, n)``.

- `Edmd`: EDMD with control (Korda & Mezic 2018). Lifting [x; thin-plate RBFs of x] with K
  centres from k-means, A and B by (optionally ridge-regularised) least squares over all
  one-step pairs. Plain least squares is what the paper compares against; on this data it comes
  out unstable (spectral radius ~1.6, docs/paper_notes.md) and a ridge does not cure it, so
  ``stabilise=True`` clips the eigenvalues of A into the unit disc after the fit.
- `Sindy`: SINDy with control, a 4th-order polynomial library of (x, u) mapping x_k to x_(k+1),
  sparse regression by pysindy's STLSQ (pysindy is the field's maintained implementation).
"""

import numbers

import numpy as np
import scipy.cluster.vq

from tsr_koopman_ctrl.learning.errors import DIVERGED
from tsr_koopman_ctrl.model.lifted import prediction_inputs


def one_step_pairs(data, who='fit'):
    """Flatten trajectories into (x_k, u_k, x_(k+1)) rows; `who` names the caller in the
    one-line error for anything but a Dataset."""
    if not all(hasattr(data, name) for name in ('x', 'u', 'h')):
        raise ValueError(f'{who} takes a Dataset (x (N, T + 1, n), u (N, T), h), got '
                         f'{type(data).__name__}')
    n = data.x.shape[2]
    return (data.x[:, :-1].reshape(-1, n), data.u.reshape(-1, 1), data.x[:, 1:].reshape(-1, n))


class Edmd:
    name = 'edmd'

    def __init__(self, lift_dim=36, ridge=0.0, stabilise=False, seed=0,
                 max_centre_samples=20_000):
        if isinstance(lift_dim, bool) or not isinstance(lift_dim, numbers.Integral) or (
                lift_dim < 1):
            raise ValueError(f'Edmd: lift_dim must be an integer >= 1, got {lift_dim!r}')
        self.lift_dim, self.ridge, self.seed = lift_dim, ridge, seed
        self.stabilise = stabilise
        self.name = 'edmd_stabilised' if stabilise else 'edmd'
        self.max_centre_samples = max_centre_samples

    def lift(self, x):
        xn = (x - self.mean) / self.std
        r2 = ((xn[:, None, :] - self.centres[None]) ** 2).sum(-1)
        with np.errstate(divide='ignore', invalid='ignore'):
            rbf = np.where(r2 > 0.0, 0.5 * r2 * np.log(r2), 0.0)   # r^2 log r
        return np.concatenate([x, rbf], axis=1)

    def fit(self, data):
        x, u, x_next = one_step_pairs(data, 'Edmd.fit')
        self.n = x.shape[1]
        self.mean, self.std = x.mean(0), x.std(0) + 1e-12
        rng = np.random.default_rng(self.seed)
        pick = rng.choice(len(x), min(len(x), self.max_centre_samples), replace=False)
        self.centres, _ = scipy.cluster.vq.kmeans2((x[pick] - self.mean) / self.std,
                                                   self.lift_dim, seed=self.seed, minit='++')
        regressors = np.concatenate([self.lift(x), u], axis=1)
        targets = self.lift(x_next)
        gram = regressors.T @ regressors
        gram += self.ridge * len(x) * np.eye(len(gram))
        solution = np.linalg.solve(gram, regressors.T @ targets)
        lifted = targets.shape[1]
        self.A, self.B = solution[:lifted].T, solution[lifted:].T
        if self.stabilise:
            self.A = clip_spectrum(self.A)
        return self

    def predict(self, x0, u):
        x0, u = fitted_inputs(self, hasattr(self, 'A'), x0, u)
        n = x0.shape[1]
        z = self.lift(x0)
        states = [z[:, :n]]
        with np.errstate(all='ignore'):
            for k in range(u.shape[1]):
                z = z @ self.A.T + u[:, k:k + 1] @ self.B.T
                states.append(z[:, :n])
        return np.stack(states, axis=1)


def fitted_inputs(model, fitted, x0, u):
    """predict's (x0, u) checked: the model fitted, the shapes as LiftedModel.predict's."""
    if not fitted:
        raise ValueError(f'{type(model).__name__}.predict before fit: call fit(dataset) first')
    return prediction_inputs(x0, u, model.n)


def clip_spectrum(a, radius=1.0):
    """A with every eigenvalue outside |lambda| <= radius scaled back onto that circle."""
    values, vectors = np.linalg.eig(a)
    large = np.abs(values) > radius
    values[large] *= radius / np.abs(values[large])
    return np.real(vectors @ np.diag(values) @ np.linalg.inv(vectors))


class Sindy:
    name = 'sindy'

    def __init__(self, degree=4, threshold=1e-4, alpha=1e-6):
        self.degree, self.threshold, self.alpha = degree, threshold, alpha

    def fit(self, data):
        import pysindy
        x, u, x_next = one_step_pairs(data, 'Sindy.fit')
        self.n = x.shape[1]
        self.model = pysindy.DiscreteSINDy(
            optimizer=pysindy.STLSQ(threshold=self.threshold, alpha=self.alpha),
            feature_library=pysindy.PolynomialLibrary(degree=self.degree))
        self.model.fit(x, t=data.h, x_next=x_next, u=u)
        return self

    def predict(self, x0, u):
        """Predicted states (N, T + 1, n). A window that leaves |x| <= errors.DIVERGED is not
        stepped further (the polynomial library would overflow): its trajectory up to there is
        returned, NaN after, and `errors.multistep_errors` counts it as diverged."""
        x0, u = fitted_inputs(self, hasattr(self, 'model'), x0, u)
        states = [x0]
        for k in range(u.shape[1]):
            current = states[-1]
            with np.errstate(invalid='ignore'):
                live = np.all(np.abs(current) <= DIVERGED, axis=1)
            step = np.full_like(current, np.nan)
            if live.any():
                with np.errstate(all='ignore'):
                    step[live] = self.model.predict(current[live], u=u[live, k:k + 1])
            states.append(step)
        return np.stack(states, axis=1)
