"""The state a lifted model evolves, and the way back to the physical state.

Near l = 0 the swing rate is ill-conditioned: theta'' has a term -2 (l'/l)(1 + theta'), while
the angular momentum l^2 (1 + theta') changes smoothly as l -> 0. A model with
``momentum_power`` p > 0 evolves

    s = (theta, L^p (1 + theta') - 1, l - 1, l'),   L = max(l, LENGTH_FLOOR),   l = 1 + x[2]

in place of x = (theta, theta', l - 1, l'): a scaled momentum in place of the swing rate. s = 0
at the deployed equilibrium, the other components are x's own (so bounds on theta, l and l'
read the same in either), and the map back, theta' = (1 + s[1]) / L^p - 1, is exact for every
state (the floor is applied the same way in both directions). p = 0 is the physical state
itself. The functions take numpy arrays or torch tensors (training differentiates through
them), the Jacobians numpy only (the NMPC's sensitivities).
"""

import numpy as np

#: Below this length the scale L^p stops shrinking: keeps the map back finite where a
#: prediction dips to l <= 0 (no trajectory the models are trained on gets that short).
LENGTH_FLOOR = 1e-2
#: The exponents a model file may give (the angular momentum itself, p = 2, multiplies the
#: error of its prediction by 1 / l^2 on the way back).
POWER_RANGE = (0.0, 2.0)


def _ops(array):
    """(concatenate, maximum) for numpy arrays or torch tensors."""
    if isinstance(array, np.ndarray):
        return np.concatenate, np.maximum
    import torch
    return torch.cat, torch.clamp_min


def _scale(x, power):
    """L^p (..., 1) from the length column of x (or s: the same column)."""
    _, maximum = _ops(x)
    return maximum(1.0 + x[..., 2:3], LENGTH_FLOOR) ** power


def to_model(x, power):
    """The model's state s of physical states x (..., 4)."""
    if not power:
        return x
    concatenate, _ = _ops(x)
    momentum = _scale(x, power) * (1.0 + x[..., 1:2]) - 1.0
    return concatenate([x[..., :1], momentum, x[..., 2:]], -1)


def to_state(s, power):
    """The physical states x of model states s (..., 4): `to_model`'s exact inverse."""
    if not power:
        return s
    concatenate, _ = _ops(s)
    rate = (1.0 + s[..., 1:2]) / _scale(s, power) - 1.0
    return concatenate([s[..., :1], rate, s[..., 2:]], -1)


def _length_slope(x, power, rate_term):
    """d L^p / dl times `rate_term`, zero where the floor holds L."""
    length = 1.0 + x[:, 2]
    floored = np.maximum(length, LENGTH_FLOOR)
    return np.where(length > LENGTH_FLOOR, power * floored ** (power - 1.0), 0.0) * rate_term


def to_model_jacobian(x, power):
    """d s / d x at physical states x (N, 4), (N, 4, 4)."""
    x = np.atleast_2d(x)
    jacobian = np.broadcast_to(np.eye(x.shape[1]), (len(x),) + (x.shape[1],) * 2).copy()
    if power:
        jacobian[:, 1, 1] = _scale(x, power)[:, 0]
        jacobian[:, 1, 2] = _length_slope(x, power, 1.0 + x[:, 1])
    return jacobian


def to_state_jacobian(s, power):
    """d x / d s at model states s (N, 4), (N, 4, 4)."""
    s = np.atleast_2d(s)
    jacobian = np.broadcast_to(np.eye(s.shape[1]), (len(s),) + (s.shape[1],) * 2).copy()
    if power:
        scale = _scale(s, power)[:, 0]
        jacobian[:, 1, 1] = 1.0 / scale
        # d/dl of (1 + s1) L^-p = -(1 + s1) L^-2p d L^p / dl.
        jacobian[:, 1, 2] = -_length_slope(s, power, (1.0 + s[:, 1]) / scale ** 2)
    return jacobian
