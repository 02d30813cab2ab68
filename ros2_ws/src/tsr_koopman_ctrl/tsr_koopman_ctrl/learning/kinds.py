"""The kinds of lifted model a training run can build, one object each.

A kind builds the torch model a run trains (new, or from a model file's tensors), gives the
tensors the model file stores, and the record (the metadata's ``structure``) from which a later
fine-tune builds the same kind again (`from_metadata`). The trainer, `save_model`, `train` and
`retrain` ask the kind what to do; none of them branches on it. Every kind saves an ordinary
model file: `model.lifted` and the controllers never see the kind.

    Dense()                      the paper's dense lifted A (`deep_koopman.DeepKoopman`)
    Block(BlockStructure(...))   observables stable by construction (`block_koopman`)
"""

import dataclasses

from tsr_koopman_ctrl.learning import block_koopman, deep_koopman
from tsr_koopman_ctrl.learning.block_koopman import BlockStructure


@dataclasses.dataclass(frozen=True)
class Dense:
    """The dense lifted model: every entry of A learned."""

    name = 'dense'

    def build(self, config, init=None, state_mean=None, state_std=None):
        """The model to train: from a model file's tensors `init` (its normalisation kept),
        else new with the given state normalisation."""
        if init is not None:
            return deep_koopman.DeepKoopman.from_numpy(init, config)
        return deep_koopman.DeepKoopman(config, state_mean, state_std)

    def tensors(self, model):
        """What the model file stores."""
        return model.to_numpy()

    def record(self, model):
        """The metadata's `structure`: none for the dense model."""
        return None


@dataclasses.dataclass(frozen=True)
class Block:
    """A = [[A_xx, A_xphi], [0, A_phi]] with A_phi stable by construction."""

    structure: BlockStructure = BlockStructure()
    name = 'block'

    def build(self, config, init=None, state_mean=None, state_std=None):
        return block_koopman.build(config, self.structure, init, state_mean, state_std)

    def tensors(self, model):
        # The A the structure builds, materialised in the file's usual layout and basis.
        return model.export_tensors()

    def record(self, model):
        # How A was built, so that a fine-tune builds it again (with the init's real modes).
        return {**self.structure.to_dict(), 'real_modes': model.real_modes}


#: The kinds by name, as `train --structure` and a model file's record name them.
KINDS = {'dense': Dense, 'block': Block}


def from_metadata(metadata):
    """The kind a model file was trained as (its metadata's `structure`; dense without one)."""
    record = dict(metadata.get('structure') or {})
    name = record.pop('kind', 'dense')
    if name not in KINDS:
        raise ValueError(f"model kind {name!r} is unknown (known: {', '.join(KINDS)})")
    if name == 'dense':
        return Dense()
    try:
        return Block(BlockStructure(**record))
    except TypeError as error:
        raise ValueError(f'model kind block: bad structure record ({error})') from None
