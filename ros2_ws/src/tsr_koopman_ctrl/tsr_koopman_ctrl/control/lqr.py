"""LQR gains and the MPC's prediction matrices: linear algebra the laws share."""

import numpy as np
import scipy.linalg
from tsr_sim import dynamics


def state_cost_matrix(q, q_cross=None):
    """Q = L L^T on the state, L lower-triangular with diagonal sqrt(q) and, below it, the
    entries `q_cross` row by row (L10, L20, L21, L30, L31, L32); no cross terms: diag(q).
    The factor form makes every setting a valid (positive semidefinite) weight, so a search
    over the cross terms wastes no trial."""
    q = np.asarray(q, dtype=float)
    if q.ndim != 1 or not np.all(q >= 0.0):
        raise ValueError(f'state weights must be numbers >= 0, got {q.tolist()}')
    factor = np.diag(np.sqrt(q))
    if q_cross is not None:
        below = np.tril_indices(q.size, -1)
        cross = np.asarray(q_cross, dtype=float)
        if cross.shape != below[0].shape:
            raise ValueError(f'{below[0].size} cross terms for {q.size} state weights, got '
                             f'{cross.size}')
        factor[below] = cross
    return factor @ factor.T


def continuous_lqr_gain(q, r):
    """K (4,) of u = 3 - K x for the plant linearised at x = 0, u = 3 (`dynamics.linearise`)
    with Q = diag(q) (q a vector) or Q = q (a 4 x 4 matrix), R = r, and the CARE's P (the
    cost-to-go x'Px)."""
    a, b = dynamics.linearise()
    r = np.atleast_2d(float(r))
    q = np.asarray(q, dtype=float)
    p = scipy.linalg.solve_continuous_are(a, b, q if q.ndim == 2 else np.diag(q), r)
    return np.linalg.solve(r, b.T @ p)[0], p


def discrete_lqr_gain(a, b, q, r):
    """K (N,) of u = -K z for z+ = A z + B u minimising sum z'Qz + r u^2, and the DARE's P."""
    if not r > 0.0:
        raise ValueError(f'R must be > 0, got {r}')
    r = np.atleast_2d(float(r))
    try:
        p = scipy.linalg.solve_discrete_are(a, b, q, r)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ValueError(f'no LQR gain for this (A, B): {error} (is it stabilisable?)')
    return np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)[0], p


def prediction_matrices(a, b, steps):
    """e_1..e_N stacked = free e_0 + forced v + drift_gain d for e+ = A e + B v + d."""
    nz = a.shape[0]
    powers = [np.eye(nz)]
    for _ in range(steps):
        powers.append(a @ powers[-1])
    free = np.vstack(powers[1:])
    forced = np.zeros((steps * nz, steps))
    drift_gain = np.zeros((steps * nz, nz))
    for k in range(1, steps + 1):
        rows = slice((k - 1) * nz, k * nz)
        for j in range(k):
            forced[rows, j] = (powers[k - 1 - j] @ b)[:, 0]
        drift_gain[rows] = sum(powers[:k])
    return free, forced, drift_gain
