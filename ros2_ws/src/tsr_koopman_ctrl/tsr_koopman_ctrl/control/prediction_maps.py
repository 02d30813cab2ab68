"""The two maps the NMPC (`control/nmpc.py`) plans with, behind one small interface.

A map advances a batch of planar states by one sample h under tensions held over the sample::

    step(x (N, n), u (N,))            -> x+ (N, n)
    step_jacobians(x, u)              -> (x+, d x+ / d x (N, n, n), d x+ / d u (N, n))
    interval(x, u, counts, exact)     -> (x after counts[i] steps, d / d x, d / d u)

`interval` is what the NMPC calls: every shooting interval of the plan in one batch, each row
advanced its own number of samples (1, 2, 3, 4, then 10 on the default grid). `MapBase` derives
it from `step_jacobians` (the rows still running advanced together, one sample at a time);
`PhysicsMap` overrides it with one CasADi function of the whole batch (`BatchFunction`).

- `PhysicsMap`: the planar equations of `tsr_sim.dynamics`, RK4 with substeps of at most
  LEAD_SUBSTEP on intervals of up to LEAD_SAMPLES samples (the grid's four lead intervals,
  where a short tether's Coriolis term is stiff) and SUBSTEP on longer ones, derivatives
  exact (CasADi's algorithmic differentiation of `tsr_sim.dynamics.symbolic_rk4`, the plant's
  one definition). One call per batch: the 39 intervals with their sensitivities are ~150,000
  operations, ~0.6 ms in CasADi's virtual machine, ~0.04 ms as native code. The native build
  (CasADi's C code, the system's C compiler, ~5 s in the background once a batch is hot or
  the law is warmed up) is cached on disk for later processes, and computes the same numbers
  bit for bit; without a compiler the virtual machine stays.
- `LearnedMap`: the relifted learned model, x+ = C (A psi_x(x) + B psi_u(x, u))
  (`LiftedModel.step`), its one-step Jacobians exact (forward mode through the networks,
  `LiftedModel.step_jacobians`). `exact=False` (the law's `sensitivities: 'start'`): each
  interval's sensitivities from the one-step Jacobian at its start only, J^c and
  sum_k J^k b (one batched Jacobian evaluation instead of one per sample; the simulated
  end states stay exact).
"""

import functools
import hashlib
import os
import pathlib
import shutil
import subprocess
import tempfile

import numpy as np
from tsr_sim import dynamics

#: RK4 substep of the physics map on the lead intervals and on the rest (tau): the former
#: physics NMPC's, fixed by its validation runs.
LEAD_SUBSTEP = 0.0025
SUBSTEP = 0.025
#: Intervals of up to this many samples take the lead substep.
LEAD_SAMPLES = 4
#: A batch function is built to native code once it has been called this often (a running
#: loop, not a test's few steps), or when the law is warmed up (`PhysicsMap.compile`).
HOT_CALLS = 50
#: The C compiler's flags: -O1 compiles the default grid in ~5 s and runs as fast as -O2
#: (~9 s); no fused multiply-add, so the native code computes what CasADi's virtual machine
#: does, bit for bit (a run does not depend on when its build finished).
COMPILER_FLAGS = ('-O1', '-fPIC', '-shared', '-ffp-contract=off')
#: '0' in the environment: no native builds (CasADi's virtual machine only).
COMPILE_VARIABLE = 'TSR_KOOPMAN_COMPILE'


class MapBase:
    """`interval` from `step` and `step_jacobians` (subclasses give those, `n` and `h`)."""

    n = dynamics.PLANAR_DIM

    def compile(self, wait=False):
        """Build what the map evaluates to native code, where it can (`PhysicsMap`)."""

    def native(self):
        """Whether what the map evaluates runs as native code built by `compile`."""
        return False

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
        #: {(samples, derivatives): CasADi function of one row, z = [x; u] (5,) -> end (4,),
        #: with derivatives [end; d end / d x row by row; d end / d u] (24,)}, and the grid
        #: functions of the cold start (`grid_function`)
        self._functions = {}
        #: {(counts, derivatives): `BatchFunction` of rows advanced counts[i] samples each},
        #: and the same by the counts' bytes (the lookup every step makes)
        self._batches, self._batches_by_bytes = {}, {}

    def substeps(self, samples):
        """RK4 substeps over `samples` samples: LEAD_SUBSTEP long at most on an interval of
        up to LEAD_SAMPLES samples (the grid's lead intervals), SUBSTEP on longer ones."""
        limit = LEAD_SUBSTEP if samples <= LEAD_SAMPLES else SUBSTEP
        return max(int(np.ceil(samples * self.h / limit - 1e-9)), 1)

    def function(self, samples, derivatives):
        """The CasADi function of one row advanced `samples` samples (`_functions`)."""
        key = (int(samples), bool(derivatives))
        if key not in self._functions:
            import casadi as ca

            from tsr_sim.dynamics import symbolic_rk4     # the plant's one definition
            x, u = ca.SX.sym('x', 4), ca.SX.sym('u')
            end, _ = symbolic_rk4(x, u, samples * self.h, self.substeps(samples))
            if derivatives:
                # Two Jacobians, not one in [x; u]: the operations the map has always run
                end = ca.vertcat(end, ca.vec(ca.jacobian(end, x).T), ca.jacobian(end, u))
            self._functions[key] = ca.Function(f'rk4_{key[0]}_{int(key[1])}',
                                               [ca.vertcat(x, u)], [end])
        return self._functions[key]

    def batch(self, counts, derivatives):
        """The `BatchFunction` of rows advanced counts[i] samples: z (5, N) -> (24 or 4, N)."""
        fast_key = (np.asarray(counts, dtype=np.int64).tobytes(), bool(derivatives))
        if fast_key in self._batches_by_bytes:
            return self._batches_by_bytes[fast_key]
        key = (tuple(int(c) for c in counts), bool(derivatives))
        if key not in self._batches and (key, self.h) in _SHARED_BATCHES:
            self._batches[key] = _SHARED_BATCHES[key, self.h]
        if key not in self._batches:
            import casadi as ca
            counts = np.array(key[0])
            rows = ca.MX.sym('z', 5, len(counts))
            pieces, order = [], []
            for samples in np.unique(counts):
                columns = np.flatnonzero(counts == samples)
                one = self.function(samples, derivatives)
                pieces.append((one.map(len(columns)) if len(columns) > 1 else one)(
                    rows[:, columns.tolist()]))
                order.extend(columns)
            out = ca.horzcat(*pieces)
            if order != sorted(order):
                out = out[:, np.argsort(order).tolist()]
            name = 'tsr_batch_' + hashlib.sha256(repr((key, self.h)).encode()).hexdigest()[:12]
            self._batches[key] = _SHARED_BATCHES[key, self.h] = BatchFunction(
                ca.Function(name, [rows], [out]), (key, self.h, LEAD_SUBSTEP, SUBSTEP))
        self._batches_by_bytes[fast_key] = self._batches[key]
        return self._batches[key]

    def compile(self, wait=False):
        """Start the native builds of every batch function built so far (`BatchFunction`;
        `wait`: until they are done)."""
        for function in self._batches.values():
            function.compile()
            if wait and function.build is not None:
                function.finish(wait=True)

    def native(self):
        return bool(self._batches) and all(function.native is not None
                                           for function in self._batches.values())

    def evaluate(self, x, u, counts, derivatives=True):
        """Rows x (m, 4), u (m,) advanced counts[i] samples: end (m, 4), with derivatives
        (end, a (m, 4, 4), b (m, 4))."""
        out = self.batch(counts, derivatives)(x, u)
        if not derivatives:
            return out
        return out[:, :4], out[:, 4:20].reshape(-1, 4, 4), out[:, 20:]

    def step(self, x, u):
        x = np.atleast_2d(x)
        return self.evaluate(x, u, _ones(len(x)), derivatives=False)

    def step_jacobians(self, x, u):
        x = np.atleast_2d(x)
        return self.evaluate(x, u, _ones(len(x)))

    def advance(self, x, u, counts):
        return self.evaluate(x, u, counts, derivatives=False)

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
        """Every row in one batch call (`batch`); exact whatever `exact` says."""
        return self.evaluate(x, u, counts)


#: The batch functions built in this process, by (counts and derivatives, h): every physics
#: map of a process (the supervisor's fallback, the safety filter's verified laws) evaluates
#: the same ones, so each is built, and built to native code, once.
_SHARED_BATCHES = {}


class BatchFunction:
    """A CasADi function of one matrix input and one output evaluated by CasADi's virtual
    machine until its native build is ready, then by that: the same operations, 5-10x
    faster. The build (CasADi's C code, the system's C compiler) runs in the background and is
    kept in a cache (`cache_path`) for every later process; without a compiler, or with
    TSR_KOOPMAN_COMPILE=0, the virtual machine stays."""

    def __init__(self, function, description):
        self.function = function
        #: The input's columns as rows (the physics map's [x, u] (N, 5); a backup rollout's
        #: one column (1, 6 + 2 samples)) and the output's (N, 4 or 24; (1, 4 samples)),
        #: bound to the evaluation (CasADi's buffers: no conversion to and from its matrices;
        #: column-major to CasADi); `evaluate`: by the native build once loaded.
        rows = function.size2_in(0)
        self.arguments = np.zeros((rows, function.size1_in(0)))
        self.results = np.zeros((rows, function.size1_out(0)))
        self.evaluate, self.bound = self.bind(function)
        self.native = None
        self.calls = 0
        #: The compiler at work (subprocess.Popen), or None.
        self.build = None
        self.path = cache_path(function.name(), description)
        if self.path is not None and self.path.exists():
            self.load()

    def __call__(self, x, u):
        """The outputs (N, 4 or 24) of rows x (N, 4) under u (N,)."""
        self.arguments[:, :4] = x
        self.arguments[:, 4] = u
        return self.run()

    def run(self):
        """The outputs of the inputs now in `arguments` (the function's one input, row by
        row): a copy of `results`."""
        if self.native is None:
            self.calls += 1
            if self.build is not None:
                self.finish()
            elif self.calls == HOT_CALLS:
                self.compile()
        self.evaluate()
        return self.results.copy()

    def bind(self, function):
        """(evaluate, the buffer that keeps the binding alive) of `function` on our arrays."""
        buffer, evaluate = function.buffer()
        buffer.set_arg(0, memoryview(self.arguments.reshape(-1)))
        buffer.set_res(0, memoryview(self.results.reshape(-1)))
        return evaluate, buffer

    def compile(self):
        """Start the native build (C code now, ~0.1 s; the compiler in the background)."""
        if self.native is not None or self.build is not None or self.path is None:
            return
        compiler = shutil.which(os.environ.get('CC', 'cc'))
        if compiler is None:
            self.path = None
            return
        import casadi as ca
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            directory = tempfile.mkdtemp(prefix='build_', dir=self.path.parent)
            source = os.path.join(directory, 'batch.c')
            generator = ca.CodeGenerator('batch.c', {'with_header': False})
            generator.add(self.function)
            generator.generate(directory + os.sep)
            # Compile, move into the cache (atomic: other processes may read it), clean up:
            # a build this process leaves running still lands for the next one.
            script = ('cc="$1" built="$2" kept="$3" directory="$4"; shift 4; '
                      '"$cc" "$@" -o "$built" && mv "$built" "$kept"; rm -rf "$directory"')
            self.build = subprocess.Popen(
                ['sh', '-c', script, 'sh', compiler, os.path.join(directory, 'batch.so'),
                 str(self.path), directory, *COMPILER_FLAGS, source],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True)
        except (OSError, RuntimeError):
            self.path = None      # (an unwritable cache: the virtual machine stays)

    def finish(self, wait=False):
        """Take the native build once the compiler is done (`wait`: wait for it)."""
        if wait:
            self.build.wait()
        if self.build.poll() is None:
            return
        self.build = None
        if self.path.exists():
            self.load()
        if self.native is None:
            self.path = None      # (a failed build is not tried again in this process)

    def load(self):
        import casadi as ca
        try:
            self.native = ca.external(self.function.name(), str(self.path))
        except RuntimeError:
            return
        self.evaluate, self.bound = self.bind(self.native)


@functools.cache
def _ones(rows):
    """Counts of one sample for `rows` rows (read only: shared)."""
    ones = np.ones(rows, dtype=np.int64)
    ones.flags.writeable = False
    return ones


@functools.cache
def _sources():
    return b''.join(pathlib.Path(module).read_bytes() for module in (dynamics.__file__, __file__))


def cache_path(name, description):
    """Where the native build of the batch function `name` is kept: a file named by a digest
    of what its code is generated from (`description`, CasADi's version, the plant's equations
    and this module), so an edit of either builds anew. None: no native builds."""
    if os.environ.get(COMPILE_VARIABLE, '1') == '0':
        return None
    import casadi as ca
    digest = hashlib.sha256(repr((description, ca.__version__, COMPILER_FLAGS)).encode())
    digest.update(_sources())
    home = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return pathlib.Path(home, 'tsr_koopman', 'casadi', f'{name}_{digest.hexdigest()[:16]}.so')
