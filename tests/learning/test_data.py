"""The training data as `train` assembles it (learning.data), called as the lab calls it."""

import numpy as np
import pytest

from tsr_koopman_ctrl.learning import data, dataset as datasets


def test_training_data_joins_files_and_boxes_seeded_from_the_data_seed(tmp_path):
    lines = []
    saved = datasets.sample(datasets.SamplingConfig(trajectories=20, seed=9))[0]
    datasets.save(saved, tmp_path / 'more.npz')
    joined = data.training_data([str(tmp_path / 'more.npz')], trajectories=30, data_seed=4,
                                log=lines.append, retrieval_trajectories=25)
    retrieval = datasets.sample(datasets.SamplingConfig(
        trajectories=25, seed=4 + 2, state_low=datasets.RETRIEVAL_BOX_LOW,
        state_high=datasets.RETRIEVAL_BOX_HIGH))[0]
    paper = datasets.sample(datasets.SamplingConfig(trajectories=30, seed=4))[0]
    np.testing.assert_array_equal(joined.x, np.concatenate([saved.x, retrieval.x, paper.x]))
    np.testing.assert_array_equal(joined.u, np.concatenate([saved.u, retrieval.u, paper.u]))
    assert [line.split(' (')[0] for line in lines] == [
        f'sampled {len(retrieval)} retrieval trajectories', f'sampled {len(paper)} trajectories']


def test_training_data_refuses_no_data_and_an_unknown_box():
    with pytest.raises(ValueError, match='no training data'):
        data.training_data(trajectories=0, log=lambda line: None)
    with pytest.raises(TypeError, match='no box retreival_trajectories'):
        data.training_data(trajectories=0, retreival_trajectories=5)


def test_the_test_set_is_the_paper_sampling_from_its_own_seed():
    np.testing.assert_array_equal(
        data.test_set(10).x,
        datasets.sample(datasets.SamplingConfig(trajectories=10, seed=datasets.TEST_SEED))[0].x)


def test_the_short_tether_box_starts_short_and_holds_its_tensions():
    short = data.training_data(trajectories=0, short_tether_trajectories=300,
                               log=lambda line: None)
    starts = short.x[:, 0]
    assert np.all(starts >= np.array(datasets.SHORT_TETHER_BOX_LOW) - 1e-12)
    assert np.all(starts <= np.array(datasets.SHORT_TETHER_BOX_HIGH) + 1e-12)
    assert np.all(1.0 + starts[:, 2] < 0.15) and len(short) > 50
    # Held for 10 steps: each block of ten tensions is one value.
    blocks = short.u[:, :30].reshape(len(short), 3, 10)
    np.testing.assert_array_equal(blocks, np.repeat(blocks[:, :, :1], 10, axis=2))
