"""The deep Koopman model in torch and its loss (paper Section III, mistakes fixed).

Structure (see `tsr_koopman_ctrl.model.lifted` for the same model in numpy)::

    z_0 = psi_x(x_0) = [x_0; Phi(x_0)]
    z_(k+1) = A z_k + B psi_ux(C z_k) psi_uu(u_k)          k = 0 .. T-1

Loss over a batch of T-step trajectories, discounted by gamma^k and normalised by the weights'
sum (docs/paper_notes.md explains why the paper's terms are changed):

- L_rec: x_k against C z_k, the state read off the predicted lifted state (the paper's
  ||x - C psi_x(x)|| is identically zero), per component scaled by the data's std.
- L_lift: z_k against psi_x(x_k) (mean squared error over the K + n coordinates, the x part
  scaled as in L_rec). (Dividing the Phi part by the batch variance of Phi, so that shrinking
  Phi cannot lower the loss, was tried and dropped: in a 3-epoch trial on 1e4 trajectories it
  doubled the 30-step error, 0.90 against 0.33.)
- L_ctrb: soft rank deficit 1 - mean_i s_i / (s_i + tol) over the singular values s_i of the
  column-normalised [B, AB, ..., A^(N-1)B] (relative to the largest): near 0 when all exceed
  `controllability_tol`, differentiable with a bounded gradient, unlike the paper's rank().
  The numerical rank is reported separately.
- L_eq (not in the paper, weight 0 by default): the squared drift per tau of the lifted model
  at the known equilibrium x = 0, u = 3, which LQR and MPC regulate to.
- L_step (not in the paper, weight 0 by default): `one_step_error`, the relative error of the
  one-step prediction from every measured state of the batch.
- L_phys (not in the paper, weight 0 by default): L_rec on the physical state read back from the
  model's own, each component scaled by its batch std. With `momentum_power` p > 0 the model
  evolves s = `model.coordinates.to_model(x, p)` in place of x (x_0 above is s_0, C z_k is s_k)
  and L_rec, L_lift and L_step are taken on s.

With `anchor_equilibrium` (not in the paper) Phi(x) - Phi(0) and psi_uu(u) - psi_uu(3) replace
Phi and psi_uu, so the equilibrium is an exact fixed point and L_eq is identically zero.
"""

import numpy as np
import torch
from torch import nn

from tsr_koopman_ctrl.model import coordinates


def mlp(inputs, hidden, layers, outputs, activation):
    act = nn.Tanh if activation == 'tanh' else nn.ELU
    modules, size = [], inputs
    for _ in range(layers):
        modules += [nn.Linear(size, hidden), act()]
        size = hidden
    modules.append(nn.Linear(size, outputs))
    return nn.Sequential(*modules)


class MonotoneMap(nn.Module):
    """psi_uu(u) = a s + b + sum_j c_j tanh(d_j s + e_j) with a, c, d > 0 (softplus): strictly
    increasing, so invertible; s = (u - mid) / half maps the tension range to [-1, 1]."""

    def __init__(self, terms, tension_range):
        super().__init__()
        low, high = tension_range
        self.mid, self.half = 0.5 * (low + high), 0.5 * (high - low)
        self.slope = nn.Parameter(torch.tensor(0.5))
        self.offset = nn.Parameter(torch.tensor(0.0))
        self.amplitude = nn.Parameter(torch.full((terms,), -3.0))
        self.steepness = nn.Parameter(torch.zeros(terms))
        self.shift = nn.Parameter(torch.linspace(-2.0, 2.0, terms))

    def forward(self, u):
        s = ((u - self.mid) / self.half).unsqueeze(-1)
        softplus = nn.functional.softplus
        bumps = softplus(self.amplitude) * torch.tanh(softplus(self.steepness) * s + self.shift)
        return (softplus(self.slope) + 1e-3) * s[..., 0] + self.offset + bumps.sum(-1)


class DeepKoopman(nn.Module):
    def __init__(self, config, state_mean=None, state_std=None):
        super().__init__()
        self.config = config
        n, lifted = config.state_dim, config.lifted_dim
        mean = torch.zeros(n) if state_mean is None else torch.as_tensor(state_mean)
        std = torch.ones(n) if state_std is None else torch.as_tensor(state_std)
        self.register_buffer('state_mean', mean.float().clone())
        self.register_buffer('state_std', std.float().clone())
        self.lift = mlp(n, config.hidden, config.layers, config.lift_dim, config.activation)
        self.input_gain = mlp(n, config.input_hidden, config.input_layers, 1, config.activation)
        self.input_map = MonotoneMap(config.input_terms, config.tension_range)
        # A starts at the identity (h is small: the lifted state barely moves per step).
        self.A = nn.Parameter(torch.eye(lifted))
        self.B = nn.Parameter(0.01 * torch.randn(lifted, 1))

    def normalise(self, x):
        return (x - self.state_mean) / self.state_std

    def model_state(self, x):
        """s, the state the model evolves, of physical states x."""
        return coordinates.to_model(x, self.config.momentum_power)

    def physical_state(self, s):
        return coordinates.to_state(s, self.config.momentum_power)

    def psi_x(self, x):
        """The lifted state of physical states x: [s; Phi(s)]."""
        s = self.model_state(x)
        phi = self.lift(self.normalise(s))
        if self.config.anchor_equilibrium:
            phi = phi - self.lift(self.normalise(torch.zeros_like(self.state_mean)))
        return torch.cat([s, phi], dim=-1)

    def psi_ux(self, s):
        """The input gain at model states s (C z)."""
        raw = self.input_gain(self.normalise(s))[..., 0]
        return self.config.min_input_gain + nn.functional.softplus(raw)

    def psi_uu(self, u):
        value = self.input_map(u)
        if self.config.anchor_equilibrium:
            tension = torch.full((), self.config.anchor_tension, device=value.device)
            value = value - self.input_map(tension)
        return value

    def psi_u(self, s, u):
        return self.psi_ux(s) * self.psi_uu(u)

    def rollout(self, z0, u):
        """Lifted predictions (B, T + 1, K + n) from z0 (B, K + n) under u (B, T)."""
        n, z = self.config.state_dim, z0
        lifted = [z]
        for k in range(u.shape[1]):
            z = z @ self.A.T + self.psi_u(z[:, :n], u[:, k]).unsqueeze(-1) * self.B.T
            lifted.append(z)
        return torch.stack(lifted, dim=1)

    def predict(self, x0, u):
        """Physical states read off the rollout, (B, T + 1, n)."""
        return self.physical_state(self.rollout(self.psi_x(x0), u)[..., :self.config.state_dim])

    def to_numpy(self):
        """Tensor name -> numpy array, in the layout `model_file` stores: a snapshot (on the
        CPU, .numpy() alone would share memory with the parameters the optimiser updates)."""
        return {name: value.detach().cpu().numpy().copy()
                for name, value in self.state_dict().items()}

    @classmethod
    def from_numpy(cls, tensors, config):
        model = cls(config)
        model.load_state_dict({k: torch.as_tensor(np.asarray(v), dtype=torch.float32)
                               for k, v in tensors.items()})
        return model


def loss_terms(model, x, u, training):
    """The loss terms (scalars) for states x (B, T + 1, n) and tensions u (B, T); `training`:
    the run's TrainingConfig."""
    config = model.config
    n = config.state_dim
    z_true = model.psi_x(x)
    z_hat = model.rollout(z_true[:, 0], u)
    steps = u.shape[1]
    weights = training.gamma ** torch.arange(1, steps + 1, dtype=x.dtype, device=x.device)
    weights = weights / weights.sum()

    state_error = ((z_hat[:, 1:, :n] - z_true[:, 1:, :n]) / model.state_std) ** 2
    reconstruction = (state_error.mean(dim=(0, 2)) * weights).sum()
    if training.weight_physical:
        scale = x[:, 1:].std(dim=(0, 1)).detach() + 1e-9
        physical_error = ((model.physical_state(z_hat[:, 1:, :n]) - x[:, 1:]) / scale) ** 2
        physical = (physical_error.mean(dim=(0, 2)) * weights).sum()
    else:
        physical = torch.zeros((), device=x.device)
    phi_true, phi_hat = z_true[:, 1:, n:], z_hat[:, 1:, n:]
    phi_error = ((phi_hat - phi_true) ** 2).mean(dim=(0, 2))
    lifted = ((state_error.mean(dim=(0, 2)) * n + phi_error * config.lift_dim)
              / config.lifted_dim * weights).sum()
    controllability = controllability_loss(model.A, model.B, training.controllability_tol)
    return (reconstruction, lifted, controllability,
            equilibrium_drift(model), one_step_error(model, z_true, u), physical)


def one_step_error(model, z_true, u):
    """Relative one-step error of the state read off z_(k+1) = A psi_x(x_k) + B psi_u(x_k, u_k),
    from every measured state of the batch: the step a feedback controller takes, since it lifts
    each new measurement. Each component is scaled by the batch std of its one-step increment
    (no gradient through it): 1 means no better than predicting no change."""
    n = model.config.state_dim
    x_now, x_next = z_true[:, :-1, :n], z_true[:, 1:, :n]
    predicted = (z_true[:, :-1] @ model.A[:n].T
                 + model.psi_u(x_now, u).unsqueeze(-1) * model.B[:n].T)
    increment_std = (x_next - x_now).std(dim=(0, 1)).detach() + 1e-9
    return (((predicted - x_next) / increment_std) ** 2).mean()


def equilibrium_drift(model):
    """Mean squared drift rate (per tau) of the lifted model at x = 0, u = its anchor (3)."""
    origin = torch.zeros(1, model.config.state_dim, device=model.A.device)
    tension = torch.full((1,), model.config.anchor_tension, device=model.A.device)
    z = model.psi_x(origin)
    drift = z @ model.A.T + model.psi_u(origin, tension).unsqueeze(-1) * model.B.T - z
    return ((drift / model.config.h) ** 2).mean()


def controllability_loss(a, b, tol):
    a, b = a.double(), b.double()   # the ratios reach 1e-10: beyond float32
    columns = [b[:, 0] / b[:, 0].norm().clamp_min(1e-12)]
    for _ in range(a.shape[0] - 1):
        column = a @ columns[-1]
        columns.append(column / column.norm().clamp_min(1e-12))
    singular = torch.linalg.svdvals(torch.stack(columns, dim=1))
    ratio = singular / singular[0]
    # Soft rank deficit: 1 - mean(s / (s + tol)). Its gradient is bounded by 1 / tol, unlike
    # log(s) or 1 / s, which would swamp the prediction terms through Adam's scaling.
    return 1.0 - (ratio / (ratio + tol)).mean()


def total_loss(model, x, u, training):
    """The weighted loss of `training` (a TrainingConfig) and its terms as floats."""
    rec, lift, ctrb, eq, step, physical = loss_terms(model, x, u, training)
    t = training
    total = (t.weight_reconstruction * rec + t.weight_lifted * lift
             + t.weight_controllability * ctrb + t.weight_equilibrium * eq
             + t.weight_one_step * step + t.weight_physical * physical)
    return total, {'reconstruction': rec.item(), 'lifted': lift.item(),
                   'controllability': ctrb.item(), 'equilibrium': eq.item(),
                   'one_step': step.item(), 'physical': physical.item()}
