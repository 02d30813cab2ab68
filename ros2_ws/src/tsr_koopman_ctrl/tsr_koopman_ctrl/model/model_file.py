"""The deep Koopman model file: its configs, tensor layout, writer and reader.

A model is a directory::

    <model>/weights.safetensors   every tensor (networks, A, B, state normalisation), no pickle
    <model>/model.json            format version, the model's config (`ModelConfig`), its
                                  training's (`TrainingConfig`), metrics, data provenance,
                                  versions

safetensors cannot carry code, so loading a model never executes anything. The reader checks
the names and shapes of every tensor against the config and turns any problem (missing, truncated,
corrupt, wrong shape, non-finite) into one `ModelFileError` line naming the file. Files that would
run code when read (a pickle: torch.save's .pt, .pkl; a model.json naming weights elsewhere or a
loader) are refused unread, in one line that says so (`refuse_code`).

Reading needs numpy and safetensors only, not torch: the controller evaluates the networks in
numpy (`tsr_koopman_ctrl.model.lifted`).
"""

import dataclasses
import json
import os
import pathlib

import numpy as np

from tsr_koopman_ctrl.model import coordinates

FORMAT = 'tsr-koopman-model'
FORMAT_VERSION = 1
WEIGHTS_FILE = 'weights.safetensors'
META_FILE = 'model.json'
ACTIVATIONS = ('tanh', 'elu')
#: Options of earlier versions, no longer offered: a model file may still name them with the value
#: that means "off" (they are then ignored); any other value is refused.
RETIRED_OPTIONS = {'scale_free_lifted_loss': False}


class ModelFileError(ValueError):
    """A model that cannot be used; the message is one line naming the file."""


#: Files that run code when read: pickles (torch.save, joblib, numpy object arrays) and source.
CODE_SUFFIXES = ('.pt', '.pth', '.pkl', '.pickle', '.joblib', '.ckpt', '.py')
#: model.json keys by which another format names its weights or the code that reads them.
CODE_KEYS = ('weights', 'weights_file', 'loader', 'module', 'class')
#: How a pickle starts: protocol 2+ (0x80), or the zip archive torch.save writes.
PICKLE_MAGIC = (b'\x80', b'PK\x03\x04')


def refuse_code(meta, meta_path):
    """ModelFileError, one line, if the model's metadata names weights other than
    weights.safetensors or code to load them: this reader reads two files by name and runs
    nothing, so such a model is refused rather than half-read."""
    for key, value in meta.items():
        named = isinstance(value, str) and value.lower().endswith(CODE_SUFFIXES)
        if key in CODE_KEYS or named:
            raise ModelFileError(f'{meta_path}: {key!r} names {value!r}: a model loads its '
                                 f'weights from {WEIGHTS_FILE} only and runs no code; refused')


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """What a model is: its networks, its coordinates, its sample period and the plant it
    holds; saved with the model as `config` and all that evaluating it needs."""

    state_dim: int = 4
    lift_dim: int = 36            # K: learned observables Phi(x); the lifted state has K + n
    hidden: int = 128             # Phi: `layers` hidden layers of `hidden` units
    layers: int = 4
    input_hidden: int = 128       # psi_ux (the state-dependent input gain): same shape
    input_layers: int = 4
    input_terms: int = 8          # tanh terms of the monotone input map psi_uu
    activation: str = 'tanh'
    #: psi_ux(x) = min_input_gain + softplus(net(x)) keeps the input gain away from zero, so
    #: u = psi_uu^-1(u_hat / psi_ux(x)) is always defined.
    min_input_gain: float = 0.05
    tension_range: tuple = (0.0, 5.0)
    h: float = 0.01
    #: Not in the paper: Phi(x) - Phi(0) and psi_uu(u) - psi_uu(u_d) (u_d = anchor_tension) in
    #: place of Phi and psi_uu, so z = 0 is psi_x(0) and u_hat = 0 is psi_u(0, u_d): the
    #: known equilibrium is an exact fixed point of the lifted model (no drift at the state
    #: LQR and MPC regulate to).
    anchor_equilibrium: bool = False
    #: The tension (N in the paper's dimensionless units) that holds the deployed equilibrium
    #: on the plant the model was trained for: 3 for the nominal plant; a model retrained on a
    #: plant whose actuator or mass differs anchors where that plant's data settles (retrain's
    #: --anchor data), since psi_uu(u) - psi_uu(3) cannot hold a plant that needs 3.33.
    anchor_tension: float = 3.0
    #: Not in the paper: the exponent p of the scaled momentum l^p (1 + theta') the model
    #: evolves in place of theta' (`model.coordinates`; 0: the physical state).
    momentum_power: float = 0.0

    def __post_init__(self):
        _positive(self, ('state_dim', 'lift_dim', 'hidden', 'layers', 'input_hidden',
                         'input_layers', 'input_terms'))
        if self.activation not in ACTIVATIONS:
            raise ValueError(f'activation must be one of {ACTIVATIONS}, got {self.activation!r}')
        if not 0.0 < self.h < float('inf'):      # NaN fails too
            raise ValueError(f'h (the sample period in tau) must be > 0 and finite, '
                             f'got {self.h}')
        if not self.tension_range[0] <= self.anchor_tension <= self.tension_range[1]:
            raise ValueError(f'anchor_tension must lie in tension_range {self.tension_range}, '
                             f'got {self.anchor_tension}')
        low, high = coordinates.POWER_RANGE
        if not low <= self.momentum_power <= high:
            raise ValueError(f'momentum_power must be in [{low}, {high}], '
                             f'got {self.momentum_power}')
        if not self.min_input_gain > 0.0:
            raise ValueError('min_input_gain must be > 0 (psi_ux must stay away from zero)')

    @property
    def lifted_dim(self):
        return self.lift_dim + self.state_dim


@dataclasses.dataclass(frozen=True)
class TrainingConfig:
    """How a model was trained: its loss and its optimisation; saved with the model as
    `training` (a fine-tune starts from it; evaluating the model never needs it)."""

    # Loss L = w_rec L_rec + w_lift L_lift + w_ctrb L_ctrb (paper: 0.5, 1.0, 0.1).
    weight_reconstruction: float = 0.5
    weight_lifted: float = 1.0
    weight_controllability: float = 0.1
    #: Not in the paper: weight of L_eq, the drift of the lifted model at the known equilibrium
    #: (x = 0, u = anchor_tension), per unit tau: z_d = psi_x(0) must be a fixed point for LQR
    #: about it.
    weight_equilibrium: float = 0.0
    #: Not in the paper: weight of L_step, the relative one-step error from every measured state
    #: (what a controller that lifts each measurement relies on).
    weight_one_step: float = 0.0
    #: Not in the paper: weight of L_phys, L_rec taken on the physical state read back from
    #: the model's own (the same as L_rec when momentum_power is 0).
    weight_physical: float = 0.0
    gamma: float = 1.0 - 1e-3
    #: L_ctrb is near zero once every normalised singular value of the controllability matrix
    #: is well above this (a differentiable stand-in for "full rank"; rank reported separately).
    controllability_tol: float = 1e-4
    epochs: int = 30
    batch_size: int = 256
    learning_rate: float = 1e-3
    final_learning_rate: float = 1e-5
    validation_fraction: float = 0.1
    seed: int = 0

    def __post_init__(self):
        _positive(self, ('epochs', 'batch_size'))
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f'gamma must be in (0, 1], got {self.gamma}')


def _positive(config, names):
    for name in names:
        if int(getattr(config, name)) < 1:
            raise ValueError(f'{name} must be >= 1, got {getattr(config, name)}')


def _names(cls):
    return tuple(f.name for f in dataclasses.fields(cls))


@dataclasses.dataclass(frozen=True)
class KoopmanConfig:
    """A training run's recipe: the model to build (`model`) and how to train it
    (`training`). Train and retrain take its fields by their flat names
    (`KoopmanConfig.from_dict({'lift_dim': 36, 'epochs': 30})`); the model file keeps the two
    apart."""

    model: ModelConfig = ModelConfig()
    training: TrainingConfig = TrainingConfig()

    @staticmethod
    def names():
        """Every field's flat name, the model's first."""
        return _names(ModelConfig) + _names(TrainingConfig)

    @classmethod
    def current_options(cls, values):
        """(`values` without retired options at their "off" value, the sorted names among them
        that are no config field)."""
        values = {k: v for k, v in values.items()
                  if not (k in RETIRED_OPTIONS and v == RETIRED_OPTIONS[k])}
        return values, sorted(set(values) - set(cls.names()))

    @classmethod
    def from_dict(cls, values):
        """From flat field names; an unknown one is a ValueError."""
        return cls().replace(**values)

    def replace(self, **values):
        """A copy with the fields named (flat names) changed."""
        values, unknown = self.current_options(values)
        if unknown:
            raise ValueError(f'unknown config keys {unknown}')
        if 'tension_range' in values:
            values['tension_range'] = tuple(values['tension_range'])
        model = {k: v for k, v in values.items() if k in _names(ModelConfig)}
        training = {k: v for k, v in values.items() if k in _names(TrainingConfig)}
        return KoopmanConfig(dataclasses.replace(self.model, **model),
                             dataclasses.replace(self.training, **training))

    def as_dict(self):
        """Every field by its flat name."""
        return {**dataclasses.asdict(self.model), **dataclasses.asdict(self.training)}

    @classmethod
    def of(cls, model, metadata):
        """The recipe a model file was trained with: its ModelConfig and the metadata's
        `training` record, as `model_file.load` returns them (checked there)."""
        return cls(model, TrainingConfig(**metadata.get('training', {})))


def weights_sha256(directory):
    """sha256 of a model directory's weights file: what names a model's weights in a bag's
    RunInfo and in a retrained model's provenance."""
    import hashlib
    with open(pathlib.Path(directory) / WEIGHTS_FILE, 'rb') as weights:
        return hashlib.sha256(weights.read()).hexdigest()


def check_free(out, overwrite=False):
    """Refuse, unless `overwrite`, an `out` that already holds a model (a shipped one, a
    finished training): a mistyped path must not replace it silently (ValueError, one line)."""
    if not overwrite and os.path.isfile(os.path.join(out, META_FILE)):
        raise ValueError(f'--out {out} already holds a model: write the new one elsewhere, or '
                         'pass --overwrite to replace it')


def mlp_shapes(prefix, inputs, hidden, layers, outputs):
    """Tensor names and shapes of an MLP stored as torch.nn.Sequential(Linear, act, ...)."""
    sizes = [inputs] + [hidden] * layers + [outputs]
    shapes = {}
    for i in range(len(sizes) - 1):
        shapes[f'{prefix}.{2 * i}.weight'] = (sizes[i + 1], sizes[i])
        shapes[f'{prefix}.{2 * i}.bias'] = (sizes[i + 1],)
    return shapes


def expected_shapes(config):
    """Name -> shape of every tensor a model with this config stores."""
    n, lifted, terms = config.state_dim, config.lifted_dim, config.input_terms
    shapes = {'state_mean': (n,), 'state_std': (n,), 'A': (lifted, lifted), 'B': (lifted, 1),
              'input_map.slope': (), 'input_map.offset': (), 'input_map.amplitude': (terms,),
              'input_map.steepness': (terms,), 'input_map.shift': (terms,)}
    shapes.update(mlp_shapes('lift', n, config.hidden, config.layers, config.lift_dim))
    shapes.update(mlp_shapes('input_gain', n, config.input_hidden, config.input_layers, 1))
    return shapes


def save(directory, tensors, config, metadata):
    """Write a model: `tensors` name -> numpy array (checked against `config`, a ModelConfig),
    `metadata` a JSON-able dict (its `training`: the TrainingConfig fields; metrics,
    provenance, ...). Files are replaced atomically."""
    from safetensors.numpy import save_file
    directory = pathlib.Path(directory)
    check_tensors(tensors, config, directory / WEIGHTS_FILE)
    directory.mkdir(parents=True, exist_ok=True)
    # np.array, not ascontiguousarray: the latter turns 0-d scalars into shape (1,).
    arrays = {name: np.array(value, dtype=np.float32) for name, value in tensors.items()}
    meta = {'format': FORMAT, 'version': FORMAT_VERSION, 'config': dataclasses.asdict(config),
            **metadata}
    umask = os.umask(0)
    os.umask(umask)
    for name, write in ((WEIGHTS_FILE, lambda p: save_file(arrays, str(p))),
                        (META_FILE, lambda p: p.write_text(json.dumps(meta, indent=2) + '\n'))):
        partial = directory / (name + '.partial')
        write(partial)
        # safetensors creates its file 0600: a model is read by whoever deploys it.
        partial.chmod(0o666 & ~umask)
        partial.replace(directory / name)


def load(directory):
    """Read a model: returns (tensors as float64 numpy arrays, config, metadata dict)."""
    directory = pathlib.Path(directory)
    meta_path, weights_path = directory / META_FILE, directory / WEIGHTS_FILE
    if not directory.is_dir():
        raise ModelFileError(f'{directory}: no such model directory')
    meta = read_metadata(meta_path)
    refuse_code(meta, meta_path)
    if not isinstance(meta.get('config'), dict):
        raise ModelFileError(f'{meta_path}: no config object (the ModelConfig fields)')
    try:
        config, meta['training'] = split_config(meta['config'], meta.get('training'))
        meta['config'] = dataclasses.asdict(config)      # one layout, whatever the file's
    except (KeyError, TypeError, ValueError) as error:
        raise ModelFileError(f'{meta_path}: bad config ({error})')
    tensors = read_weights(weights_path)
    check_tensors(tensors, config, weights_path)
    return {k: v.astype(np.float64) for k, v in tensors.items()}, config, meta


def split_config(values, training=None):
    """(ModelConfig, the TrainingConfig fields) of a model file's `config` and `training`.
    A file may hold both in `config` (the flat layout), or some of the training's there: each
    training field is taken from wherever the file gives it, and one given twice with two
    values, or a `training` key that is no TrainingConfig field, is a ValueError."""
    values, unknown = KoopmanConfig.current_options(values)
    record, _ = KoopmanConfig.current_options(dict(training or {}))
    stray = sorted(set(record) - set(_names(TrainingConfig)))
    if unknown or stray:
        raise ValueError(f'unknown config keys {unknown}' if unknown else
                         f'training keys {stray} are no TrainingConfig fields')
    clash = sorted(k for k in set(values) & set(record) if values[k] != record[k])
    if clash:
        raise ValueError(f'config and training give {clash} two values')
    recipe = KoopmanConfig().replace(**{**record, **values})
    return recipe.model, dataclasses.asdict(recipe.training)


def read_metadata(path):
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise ModelFileError(f'{path}: missing')
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ModelFileError(f'{path}: not valid JSON ({error})')
    if not isinstance(meta, dict) or meta.get('format') != FORMAT:
        raise ModelFileError(f'{path}: not a {FORMAT} metadata file')
    if meta.get('version') != FORMAT_VERSION:
        raise ModelFileError(f'{path}: format version {meta.get("version")}, this code reads '
                             f'{FORMAT_VERSION}')
    return meta


def read_weights(path):
    """The tensors of a safetensors file (which holds no code: reading it runs nothing)."""
    from safetensors import SafetensorError
    from safetensors.numpy import load_file
    try:
        return load_file(str(path))
    except FileNotFoundError:
        code = sorted(p.name for p in path.parent.iterdir()
                      if p.suffix.lower() in CODE_SUFFIXES)
        also = (f' ({", ".join(code)}: a pickle runs code when read; a model is never read '
                'from one)') if code else ''
        raise ModelFileError(f'{path}: missing{also}')
    except (SafetensorError, OSError, ValueError) as error:
        if _starts_like_a_pickle(path):
            raise ModelFileError(f'{path}: a pickle (torch.save or pickle), not safetensors: '
                                 'refused unread (a pickle runs code when read)')
        raise ModelFileError(f'{path}: corrupt or truncated ({error})')


def _starts_like_a_pickle(path):
    try:
        with open(path, 'rb') as f:
            start = f.read(4)
    except OSError:
        return False
    return start.startswith(PICKLE_MAGIC)


def check_tensors(tensors, config, path):
    expected = expected_shapes(config)
    missing = sorted(set(expected) - set(tensors))
    extra = sorted(set(tensors) - set(expected))
    if missing or extra:
        raise ModelFileError(f'{path}: tensors do not match the config (missing {missing}, '
                             f'unexpected {extra})')
    for name, shape in expected.items():
        value = np.asarray(tensors[name])
        if value.shape != shape:
            raise ModelFileError(f'{path}: {name} has shape {value.shape}, the config needs '
                                 f'{shape}')
        if not np.all(np.isfinite(value)):
            raise ModelFileError(f'{path}: {name} has non-finite values')
