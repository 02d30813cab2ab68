"""A deep Koopman model whose only unstable modes can be the state's own (training only).

`deep_koopman.DeepKoopman` learns a dense lifted A. Trained for prediction (koopman_default) it
has unstable modes up to 1.11 per step that B barely reaches, and the lifted LQR on it fails from
every start. `BlockKoopman` changes only how A is built::

    A = [[A_xx    A_xphi ]      n free rows: the state's own update, as before
         [ 0      A_phi  ]]     the observables evolve on their own (no x -> Phi coupling)

    A_phi = blockdiag(lambda_1, ..., lambda_m, sigma_1 R(omega_1), ..., sigma_p R(omega_p))
    lambda_i = rho tanh(a_i),  sigma_j = rho sigmoid(s_j),  R(w) = [[cos w, -sin w],
                                                                     [sin w,  cos w]]

so eig(A) = eig(A_xx) U eig(A_phi) with every observable eigenvalue strictly inside |z| < rho
(`radius`, 1 by default): only the n modes of A_xx can be unstable, and they carry the plant's
own instability (1.0128 per step at x = 0). The real block-diagonal form costs no generality for
a diagonalisable A_phi: the lifting network's last layer absorbs any change of basis of Phi.

Two options, both on in koopman_block: `flat` trains on the observables Phi(x) - Phi(0) -
Phi'(0) x, which vanish to first order at the equilibrium, so the model's linearisation there is
A_xx's alone; without `observable_input`, B = [B_x; 0] (the input reaches the observables only
through x). The loss, the networks and the input map are DeepKoopman's.

The structure only matters while training: `export_tensors` writes the materialised A (and B)
in the model file's usual layout and basis, z = [x; Phi(x) - Phi(0)], so `model.lifted` and
every controller use the model as they use any other. A flat model's tensors are mapped there by
T = [[I, 0], [D, I]] (D = dPhi/dx(0)): A = T A_flat T^-1, B = T B_flat, which keeps the
eigenvalues, the predictions (C T = C) and the LQR law with Q' = C^T diag(q) C.
"""

import dataclasses

import numpy as np
import torch
from torch import nn

from tsr_koopman_ctrl.learning.deep_koopman import DeepKoopman
from tsr_koopman_ctrl.model.lifted import LiftedModel

#: Parameters that exist only in training; the model file stores the A they build.
STRUCTURE_PARAMETERS = ('top', 'real_raw', 'pair_raw', 'pair_angle')


@dataclasses.dataclass(frozen=True)
class BlockStructure:
    """How `BlockKoopman` builds A (saved in the model file's metadata as `structure`)."""

    #: Real observable eigenvalues of a new model (the rest in pairs); from an init, the init's.
    real_modes: int = 12
    #: Every observable eigenvalue lies strictly inside |z| < radius.
    radius: float = 1.0
    #: From an init: its observable eigenvalues beyond margin * radius are pulled in to there.
    margin: float = 0.995
    flat: bool = True
    observable_input: bool = False

    def __post_init__(self):
        if not (self.radius > 0.0 and 0.0 < self.margin < 1.0 and self.real_modes >= 0):
            raise ValueError(f'block structure needs radius > 0, 0 < margin < 1 and '
                             f'real_modes >= 0, got {self}')

    def to_dict(self):
        return {'kind': 'block', **dataclasses.asdict(self)}


class BlockKoopman(DeepKoopman):
    """DeepKoopman with A = [[A_xx, A_xphi], [0, A_phi]], A_phi stable by construction."""

    def __init__(self, config, state_mean=None, state_std=None, structure=None):
        super().__init__(config, state_mean, state_std)
        structure = structure or BlockStructure()
        self.structure = structure
        n, k = config.state_dim, config.lift_dim
        if structure.real_modes > k or (k - structure.real_modes) % 2:
            raise ValueError(f'lift_dim - real_modes must be even and >= 0, got {k}, '
                             f'{structure.real_modes}')
        if not structure.observable_input:
            # B[n:] starts at 0 and gets no gradient, so Adam leaves it at 0.
            mask = torch.zeros(config.lifted_dim, 1)
            mask[:n] = 1.0
            with torch.no_grad():
                self.B.mul_(mask)
            self.B.register_hook(lambda grad: grad * mask.to(grad.device))
        del self.A   # the dense parameter; the property below builds A
        self.radius = float(structure.radius)
        self.real_modes, self.pairs = structure.real_modes, (k - structure.real_modes) // 2
        self.top = nn.Parameter(torch.eye(n, n + k))
        # Start slow, as DeepKoopman's A = I does: real eigenvalues 0.9..0.995, pairs at 0.99
        # turning by 0.01..0.5 rad per step.
        self.real_raw = nn.Parameter(torch.atanh(torch.linspace(0.9, 0.995, self.real_modes)))
        self.pair_raw = nn.Parameter(torch.full((self.pairs,), float(np.log(0.99 / 0.01))))
        self.pair_angle = nn.Parameter(torch.linspace(0.01, 0.5, self.pairs))
        m = self.real_modes
        first = m + 2 * torch.arange(self.pairs)
        rows = torch.cat([torch.arange(m), first, first + 1, first, first + 1])
        cols = torch.cat([torch.arange(m), first, first + 1, first + 1, first])
        self.register_buffer('phi_rows', rows + n, persistent=False)
        self.register_buffer('phi_cols', cols + n, persistent=False)

    def anchor_jacobian(self):
        """d lift(normalise(x)) / dx at x = 0 (K x n), exact and differentiable."""
        h = self.normalise(torch.zeros_like(self.state_mean))
        jacobian = torch.diag(1.0 / self.state_std)
        for layer in self.lift:
            if isinstance(layer, nn.Linear):
                h = layer(h)
                jacobian = layer.weight @ jacobian
            elif isinstance(layer, nn.Tanh):
                h = torch.tanh(h)
                jacobian = (1.0 - h ** 2).unsqueeze(-1) * jacobian
            else:   # ELU
                jacobian = torch.where(h > 0.0, 1.0, torch.exp(h)).unsqueeze(-1) * jacobian
                h = layer(h)
        return jacobian

    def psi_x(self, x):
        z = super().psi_x(x)
        if not self.structure.flat:
            return z
        n = self.config.state_dim
        return torch.cat([z[..., :n], z[..., n:] - x @ self.anchor_jacobian().T], dim=-1)

    def observable_eigenvalues(self):
        """(real eigenvalues, pair moduli, pair angles) of A_phi."""
        return (self.radius * torch.tanh(self.real_raw),
                self.radius * torch.sigmoid(self.pair_raw), self.pair_angle)

    @property
    def A(self):
        real, modulus, angle = self.observable_eigenvalues()
        cos, sin = modulus * torch.cos(angle), modulus * torch.sin(angle)
        values = torch.cat([real, cos, cos, -sin, sin])
        n, size = self.config.state_dim, self.config.lifted_dim
        full = torch.zeros(size, size, dtype=self.top.dtype, device=self.top.device)
        full = full.index_put((self.phi_rows, self.phi_cols), values)
        return torch.cat([self.top, full[n:]])

    def rollout(self, z0, u):
        """As DeepKoopman's, with A built once per call."""
        a, n, z = self.A, self.config.state_dim, z0
        lifted = [z]
        for k in range(u.shape[1]):
            z = z @ a.T + self.psi_u(z[:, :n], u[:, k]).unsqueeze(-1) * self.B.T
            lifted.append(z)
        return torch.stack(lifted, dim=1)

    def export_tensors(self):
        """The model file's tensors (`model_file.expected_shapes`) in its basis, A and B
        materialised; copies, never views of the live parameters."""
        tensors = {name: value.detach().cpu().double().numpy().copy()
                   for name, value in self.state_dict().items()
                   if name not in STRUCTURE_PARAMETERS}
        with torch.no_grad():
            a = self.A.double().cpu().numpy()
            b = self.B.double().cpu().numpy()
            if self.structure.flat:
                t = flat_basis(self.anchor_jacobian().double().cpu().numpy(),
                               self.config.lifted_dim)
                a, b = t @ a @ np.linalg.inv(t), t @ b
        tensors['A'], tensors['B'] = a.copy(), b.copy()
        return tensors


def flat_basis(jacobian, lifted_dim):
    """T = [[I, 0], [D, I]] with D (K x n) the lifting's Jacobian at 0: z = T z_flat."""
    n = jacobian.shape[1]
    t = np.eye(lifted_dim)
    t[n:, :n] = jacobian
    return t


def real_block_form(a_phi):
    """(T, real eigenvalues, upper complex eigenvalues) of a_phi: T^-1 a_phi T is block diagonal,
    the real eigenvalues first, then a 2 x 2 block [[a, -b], [b, a]] per pair a +- ib."""
    values, vectors = np.linalg.eig(a_phi)
    columns, real_values, pair_values = [], [], []
    for i in np.flatnonzero(np.abs(values.imag) < 1e-9):
        v = vectors[:, i].real
        columns.append(v / np.linalg.norm(v))
        real_values.append(values[i].real)
    for i in np.flatnonzero(values.imag >= 1e-9):
        # A [vr, -vi] = [vr, -vi] [[a, -b], [b, a]] for lambda = a + ib with eigenvector vr + ivi.
        v = vectors[:, i]
        scale = np.linalg.norm(v)
        columns += [v.real / scale, -v.imag / scale]
        pair_values.append(values[i])
    return np.stack(columns, axis=1), np.array(real_values), np.array(pair_values)


def from_tensors(tensors, config, structure=None):
    """A BlockKoopman initialised from a model file's tensors (any A): A_phi's real eigenbasis
    becomes the observables' basis (the lifting's last layer, A_xphi and B_phi transformed), the
    x -> Phi coupling is dropped and observable eigenvalues beyond margin * radius are pulled
    in to there. The number of real modes is the init's (the structure's is ignored)."""
    structure = structure or BlockStructure()
    n = config.state_dim
    a = np.asarray(tensors['A'], dtype=float)
    b = np.array(tensors['B'], dtype=float)
    if structure.flat:
        # The observables' Jacobian at the anchor (K x n), exact, in float64.
        jacobian = LiftedModel(tensors, config).lift_jacobian()[n:]
        t = flat_basis(jacobian, config.lifted_dim)
        a, b = np.linalg.solve(t, a @ t), np.linalg.solve(t, b)
    basis, real_values, pair_values = real_block_form(a[n:, n:])
    structure = dataclasses.replace(structure, real_modes=len(real_values))
    model = BlockKoopman(config, tensors['state_mean'], tensors['state_std'], structure)
    inverse = np.linalg.inv(basis)
    state = {k: torch.as_tensor(np.asarray(v), dtype=torch.float32)
             for k, v in tensors.items() if k != 'A'}
    last = max(int(k.split('.')[1]) for k in tensors if k.startswith('lift.'))
    for part in ('weight', 'bias'):
        name = f'lift.{last}.{part}'
        state[name] = torch.as_tensor(inverse @ tensors[name], dtype=torch.float32)
    b[n:] = 0.0 if not structure.observable_input else inverse @ b[n:]
    radius, margin = structure.radius, structure.margin
    real = np.clip(real_values / radius, -margin, margin)
    modulus = np.clip(np.abs(pair_values), 1e-3 * radius, margin * radius) / radius
    state.update({
        'B': torch.as_tensor(b, dtype=torch.float32),
        'top': torch.as_tensor(np.concatenate([a[:n, :n], a[:n, n:] @ basis], axis=1),
                               dtype=torch.float32),
        'real_raw': torch.as_tensor(np.arctanh(real), dtype=torch.float32),
        'pair_raw': torch.as_tensor(np.log(modulus / (1.0 - modulus)), dtype=torch.float32),
        'pair_angle': torch.as_tensor(np.angle(pair_values), dtype=torch.float32)})
    model.load_state_dict(state)
    return model


def build(config, structure, init=None, state_mean=None, state_std=None):
    """The trainer's BlockKoopman: from a model file's tensors `init`, else new with the given
    state normalisation."""
    if config.momentum_power:
        raise ValueError('a block model evolves the physical state: momentum_power must be 0')
    if init is not None:
        return from_tensors(init, config, structure)
    return BlockKoopman(config, state_mean, state_std, structure)
