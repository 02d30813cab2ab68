"""The training data of a model as `train` assembles it: dataset files, the paper's sampled
trajectories and the extra sampled boxes, and the held-out test set. The `train` command and the
lab call these alike.

    from tsr_koopman_ctrl.learning import data
    training = data.training_data(['more.npz'], trajectories=40_000, data_seed=0,
                                  retrieval_trajectories=4_000)
    test = data.test_set(5_000)
"""

from tsr_sim import dynamics

from tsr_koopman_ctrl.learning import dataset as datasets

#: Extra sampled data beyond the paper's (not in it): the keyword of `training_data` giving the
#: count, the seed offset from data_seed, the box of initial states, further sampling settings,
#: and what the progress line calls them.
EXTRA_BOXES = (
    ('equilibrium_trajectories', 1, datasets.EQUILIBRIUM_BOX_LOW, datasets.EQUILIBRIUM_BOX_HIGH,
     {}, 'trajectories near the equilibrium'),
    ('retrieval_trajectories', 2, datasets.RETRIEVAL_BOX_LOW, datasets.RETRIEVAL_BOX_HIGH, {},
     'retrieval trajectories'),
    ('held_tension_trajectories', 3, dynamics.TABLE1_STATE_LOW, dynamics.TABLE1_STATE_HIGH,
     datasets.HELD_TENSIONS, 'held-tension trajectories'),
    ('short_tether_trajectories', 4, datasets.SHORT_TETHER_BOX_LOW,
     datasets.SHORT_TETHER_BOX_HIGH, datasets.HELD_TENSIONS, 'short-tether trajectories'))


def training_data(files=(), trajectories=40_000, data_seed=0, log=print, **extra):
    """One Dataset: the dataset `files`, each extra box whose count is given (`extra`: a name
    of EXTRA_BOXES and a count), then `trajectories` sampled with the paper's settings (0:
    none), each sampled part seeded from `data_seed`. `log`: a line per sampled part.
    ValueError if that is no data at all; TypeError for an unknown box."""
    names = [box[0] for box in EXTRA_BOXES]
    unknown = sorted(set(extra) - set(names))
    if unknown:
        raise TypeError(f'training_data: no box {", ".join(unknown)} (boxes: '
                        f'{", ".join(names)})')
    parts = [datasets.load(path) for path in files]
    for name, seed_offset, low, high, settings, label in EXTRA_BOXES:
        count = extra.get(name) or 0
        if count > 0:
            sampled, dropped = datasets.sample(datasets.SamplingConfig(
                trajectories=count, seed=data_seed + seed_offset,
                state_low=tuple(float(v) for v in low), state_high=tuple(float(v) for v in high),
                **settings))
            log(f'sampled {len(sampled)} {label} ({dropped} dropped)')
            parts.append(sampled)
    if trajectories > 0:
        sampled, dropped = datasets.sample(datasets.SamplingConfig(
            trajectories=trajectories, seed=data_seed))
        log(f'sampled {len(sampled)} trajectories ({dropped} runaways dropped)')
        parts.append(sampled)
    if not parts:
        raise ValueError('no training data: give --trajectories > 0 or --data FILE')
    return datasets.concatenate(parts)


def test_set(trajectories, seed=datasets.TEST_SEED):
    """The held-out test set: `trajectories` sampled with the paper's settings from `seed`
    (never a training seed), whose errors a model file records."""
    data, _ = datasets.sample(datasets.SamplingConfig(trajectories=trajectories, seed=seed))
    return data
