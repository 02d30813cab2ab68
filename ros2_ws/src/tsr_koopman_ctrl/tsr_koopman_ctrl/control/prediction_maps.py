"""The two maps the NMPC (`control/nmpc.py`) plans with, behind one small interface.

A map advances a batch of planar states by one sample h under tensions held over the sample::

    step(x (N, n), u (N,))            -> x+ (N, n)
    step_jacobians(x, u)              -> (x+, d x+ / d x (N, n, n), d x+ / d u (N, n))
    interval(x, u, counts, exact)     -> (x after counts[i] steps, d / d x, d / d u)

`interval` is what the NMPC calls: every shooting interval of the plan in one batch, each row
advanced its own number of samples (1, 2, 3, 4, then 10 on the default grid). `MapBase` derives
it from `step_jacobians` (the rows still running advanced together, one sample at a time);
`PhysicsMap` overrides it with one CasADi function per interval length.

- `PhysicsMap`: the planar equations of `tsr_sim.dynamics`, RK4 with substeps of at most
  LEAD_SUBSTEP on intervals of up to LEAD_SAMPLES samples (the grid's four lead intervals,
  where a short tether's Coriolis term is stiff) and SUBSTEP on longer ones, derivatives
  exact (CasADi's algorithmic differentiation of `tsr_sim.dynamics.symbolic_rk4`, the plant's
  one definition; interpreted, not compiled: 0.1-0.3 ms for the 39 intervals).
- `LearnedMap`: the relifted learned model, x+ = C (A psi_x(x) + B psi_u(x, u))
  (`LiftedModel.step`), its one-step Jacobians exact (forward mode through the networks,
  `LiftedModel.step_jacobians`). `exact=False` (the law's `sensitivities: 'start'`): each
  interval's sensitivities from the one-step Jacobian at its start only, J^c and
  sum_k J^k b (one batched Jacobian evaluation instead of one per sample; the simulated
  end states stay exact).
"""

import numpy as np
from tsr_sim import dynamics

#: RK4 substep of the physics map on the lead intervals and on the rest (tau): the former
#: physics NMPC's, fixed by its validation runs.
LEAD_SUBSTEP = 0.0025
SUBSTEP = 0.025
#: Intervals of up to this many samples take the lead substep.
LEAD_SAMPLES = 4


class MapBase:
    """`interval` from `step` and `step_jacobians` (subclasses give those, `n` and `h`)."""

    n = dynamics.PLANAR_DIM

    def advance(self, x, u, counts):
        """Rows of x (N, n) advanced counts[i] samples under u[i], no derivatives: (N, n)."""
        end, u, counts = np.array(x, dtype=float), np.asarray(u, dtype=float), np.asarray(counts)
        for k in range(int(counts.max())):
            active = np.flatnonzero(counts > k)
            end[active] = self.step(end[active], u[active])
        return end

    def rollout(self, x, u, counts):
        """One state x (n,) flown through the intervals in turn, u[j] held over counts[j]
        samples: the node states (N + 1, n), sequential (a cold start's single shooting)."""
        nodes = [np.asarray(x, dtype=float)]
        with np.errstate(all='ignore'):
            for tension, count in zip(u, counts):
                nodes.append(self.advance(nodes[-1][None], np.array([tension]), [count])[0])
        return np.array(nodes)

    def feedback_rollout(self, x, tension, gain, bounds, counts):
        """One state x (n,) flown through the intervals under the linear law
        u = clip(tension - gain x, *bounds), evaluated at each interval's start and held over
        it: (tensions (N,), node states (N + 1, n)), sequential."""
        nodes, plan = [np.asarray(x, dtype=float)], []
        with np.errstate(all='ignore'):
            for count in counts:
                plan.append(float(np.clip(tension - gain @ nodes[-1], *bounds)))
                nodes.append(self.advance(nodes[-1][None], np.array([plan[-1]]), [count])[0])
        return np.array(plan), np.array(nodes)

    def interval(self, x, u, counts, exact=True):
        """Rows of x (N, n) advanced counts[i] >= 1 samples under u[i]: (end (N, n),
        d end / d x (N, n, n), d end / d u (N, n)). `exact` False: the sensitivities from the
        one-step Jacobian at each row's start (see the module docstring)."""
        x, u = np.array(x, dtype=float), np.asarray(u, dtype=float)
        counts = np.asarray(counts)
        end, d_state, d_tension = self.step_jacobians(x, u)
        end = end.astype(float)    # the states carried in float64 whatever the map's type
        if exact:
            a, b = d_state.copy(), d_tension.copy()
        else:
            a, b = _held_powers(d_state, d_tension, counts)
        for k in range(1, int(counts.max())):
            active = np.flatnonzero(counts > k)
            if exact:
                end[active], d_state, d_tension = self.step_jacobians(end[active], u[active])
                a[active] = d_state @ a[active]
                b[active] = np.einsum('nij,nj->ni', d_state, b[active]) + d_tension
            else:
                end[active] = self.step(end[active], u[active])
        return end, a.astype(float, copy=False), b.astype(float, copy=False)


def _held_powers(d_state, d_tension, counts):
    """(J^c, sum_{k<c} J^k b) per row: an interval's sensitivities with the one-step Jacobians
    (J, b) at its start held over its c samples."""
    a, b = d_state.copy(), d_tension.copy()
    for k in range(1, int(counts.max())):
        active = np.flatnonzero(counts > k)
        j = d_state[active]
        b[active] = np.einsum('nij,nj->ni', j, b[active]) + d_tension[active]
        a[active] = j @ a[active]
    return a, b


class LearnedMap(MapBase):
    """The relifted learned model as the NMPC's map (module docstring)."""

    def __init__(self, model, dtype=np.float64):
        #: The model as loaded (float64) and the copy the map evaluates (`dtype`).
        self.model = model
        self.evaluated = model if np.dtype(dtype) == np.float64 else model.astype(dtype)
        self.n = model.n
        self.h = float(model.config.h)

    def step(self, x, u):
        return self.evaluated.step(np.atleast_2d(x), u)

    def step_jacobians(self, x, u):
        return self.evaluated.step_jacobians(x, u)


class PhysicsMap(MapBase):
    """The planar equations, RK4 with substeps, as the NMPC's map (module docstring). Casadi
    is imported here only, when one is built."""

    def __init__(self, h=dynamics.PAPER_STEP):
        self.h = float(h)
        #: {(samples, rows): CasADi function (x (4, rows), u (1, rows)) -> (end, d/dx, d/du)}
        self._functions = {}

    def substeps(self, samples):
        """RK4 substeps over `samples` samples: LEAD_SUBSTEP long at most on an interval of
        up to LEAD_SAMPLES samples (the grid's lead intervals), SUBSTEP on longer ones."""
        limit = LEAD_SUBSTEP if samples <= LEAD_SAMPLES else SUBSTEP
        return max(int(np.ceil(samples * self.h / limit - 1e-9)), 1)

    def function(self, samples, rows):
        key = (int(samples), int(rows))
        if key not in self._functions:
            import casadi as ca

            from tsr_sim.dynamics import symbolic_rk4     # the plant's one definition
            x, u = ca.SX.sym('x', 4), ca.SX.sym('u')
            end, _ = symbolic_rk4(x, u, samples * self.h, self.substeps(samples))
            function = ca.Function(f'rk4_{samples}', [x, u],
                                   [end, ca.jacobian(end, x), ca.jacobian(end, u)])
            self._functions[key] = function.map(rows) if rows > 1 else function
        return self._functions[key]

    def evaluate(self, samples, x, u):
        """Rows x (m, 4), u (m,) advanced `samples` samples: (end (m, 4), a (m, 4, 4),
        b (m, 4))."""
        m = len(x)
        end, a, b = self.function(samples, m)(x.T, u[None, :])
        a = np.asarray(a).reshape(4, m, 4).transpose(1, 0, 2)
        return np.asarray(end).T, a, np.asarray(b).T

    def step(self, x, u):
        return self.step_jacobians(x, u)[0]

    def step_jacobians(self, x, u):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.broadcast_to(np.asarray(u, dtype=float), (len(x),))
        return self.evaluate(1, x, u)

    def advance(self, x, u, counts):
        return self.interval(x, u, counts)[0]

    def rollout(self, x, u, counts):
        """`MapBase.rollout` in one CasADi call (a function per grid, built once)."""
        function = self.grid_function('rollout', counts, lambda start, node, j, inputs:
                                      inputs[j], len(counts))
        with np.errstate(all='ignore'):
            return np.asarray(function(np.asarray(x, dtype=float),
                                       np.asarray(u, dtype=float))[1]).T

    def feedback_rollout(self, x, tension, gain, bounds, counts):
        """`MapBase.feedback_rollout` in one CasADi call (a function per grid)."""
        def law(start, node, j, inputs):
            import casadi as ca
            u = inputs[0] - ca.dot(inputs[1:5], node)
            return ca.fmin(ca.fmax(u, inputs[5]), inputs[6])
        function = self.grid_function('feedback', counts, law, 7)
        inputs = np.r_[tension, np.asarray(gain, dtype=float).ravel(), bounds]
        with np.errstate(all='ignore'):
            plan, nodes = function(np.asarray(x, dtype=float), inputs)
        return np.asarray(plan).ravel(), np.asarray(nodes).T

    def grid_function(self, kind, counts, tension, inputs):
        """A CasADi function (x (4), inputs) -> (tensions (N,), nodes (4, N + 1)) flying the
        grid `counts` from x, interval j under tension(x, node_j, j, inputs), built once."""
        key = (kind, tuple(int(c) for c in counts))
        if key not in self._functions:
            import casadi as ca

            from tsr_sim.dynamics import symbolic_rk4
            start, values = ca.SX.sym('x', 4), ca.SX.sym('inputs', inputs)
            nodes, plan = [start], []
            for j, samples in enumerate(key[1]):
                plan.append(tension(start, nodes[-1], j, values))
                end, _ = symbolic_rk4(nodes[-1], plan[-1], samples * self.h,
                                      self.substeps(samples))
                nodes.append(end)
            self._functions[key] = ca.Function(kind, [start, values],
                                               [ca.vertcat(*plan), ca.horzcat(*nodes)])
        return self._functions[key]

    def interval(self, x, u, counts, exact=True):
        """The rows of each length in one mapped call; exact whatever `exact` says."""
        x, u = np.atleast_2d(np.asarray(x, dtype=float)), np.asarray(u, dtype=float)
        counts = np.asarray(counts, dtype=int)
        end, a, b = np.empty_like(x), np.empty((len(x), 4, 4)), np.empty_like(x)
        for samples in np.unique(counts):
            rows = np.flatnonzero(counts == samples)
            end[rows], a[rows], b[rows] = self.evaluate(samples, x[rows], u[rows])
        return end, a, b
