"""The paper's sampler, the dataset file and windows cut from a recorded loop."""

import numpy as np
import pytest
from tsr_sim import dynamics

from tsr_koopman_ctrl.learning import dataset as datasets


def test_sampler_follows_table1_and_drops_runaways():
    config = datasets.SamplingConfig(trajectories=3000, seed=7, substeps=1)
    data, dropped = datasets.sample(config)
    assert len(data) + dropped == 3000 and dropped > 0   # the paper's ranges do run away
    assert np.all(data.x[:, 0] >= dynamics.TABLE1_STATE_LOW)
    assert np.all(data.x[:, 0] <= dynamics.TABLE1_STATE_HIGH)
    assert data.u.min() >= 0.0 and data.u.max() <= 5.0 and data.u.shape[1] == 30
    assert np.all(np.abs(data.x) <= config.max_abs_state)
    # Every kept trajectory is the plant's own response to its tensions.
    check = dynamics.rollout(data.x[:50, 0], data.u[:50], config.h, config.substeps)
    np.testing.assert_allclose(check, data.x[:50], rtol=0, atol=1e-12)
    again, _ = datasets.sample(config)
    np.testing.assert_array_equal(again.x, data.x)
    assert data.provenance[0]['dropped'] == dropped and data.provenance[0]['seed'] == 7


def test_held_tensions_are_blocks_with_the_asked_share_at_the_ends():
    config = datasets.SamplingConfig(trajectories=4000, steps=30, **datasets.HELD_TENSIONS)
    u = datasets.tensions(config, np.random.default_rng(3))
    blocks = u.reshape(4000, 3, 10)
    assert np.all(blocks == blocks[:, :, :1])            # held for 10 steps
    at_ends = np.isin(blocks[:, :, 0], (0.0, 5.0)).mean()
    assert abs(at_ends - 2.0 / 3.0) < 0.02               # 12 000 blocks: sd 0.004
    assert abs((blocks[:, :, 0] == 5.0).mean() - 1.0 / 3.0) < 0.02
    assert u.min() >= 0.0 and u.max() <= 5.0
    # The default is the paper's: a fresh uniform tension every step, the same stream as before.
    paper = datasets.SamplingConfig(trajectories=5, steps=7)
    np.testing.assert_array_equal(datasets.tensions(paper, np.random.default_rng(1)),
                                  np.random.default_rng(1).uniform(0.0, 5.0, (5, 7)))
    with pytest.raises(ValueError, match='tension_hold'):
        datasets.SamplingConfig(tension_hold=0)


def test_dataset_file_round_trip_and_errors(small_data, tmp_path):
    path = tmp_path / 'd.npz'
    datasets.save(small_data, path)
    loaded = datasets.load(path)
    np.testing.assert_array_equal(loaded.x, small_data.x)
    np.testing.assert_array_equal(loaded.u, small_data.u)
    assert loaded.provenance == small_data.provenance and loaded.h == small_data.h
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(ValueError, match='d.npz: not a readable dataset'):
        datasets.load(path)
    with pytest.raises(ValueError, match='no such dataset'):
        datasets.load(tmp_path / 'missing.npz')
    path.write_text('not an archive')       # np.load alone would suggest allow_pickle
    with pytest.raises(ValueError, match=r'd.npz: not a readable dataset file \(the .npz'):
        datasets.load(path)


def test_windows_from_a_recorded_loop_skip_gaps_and_missing_commands():
    steps = np.r_[np.arange(0, 70), np.arange(80, 150)]
    x = np.random.default_rng(0).normal(size=(len(steps), 4))
    u = np.full(len(steps), 3.0)
    u[100] = np.nan
    data = datasets.from_loop({'step': steps, 'x': x, 'u': u}, steps=30, source='b')
    # Windows start at 0, 30 (ok), 60 (gap 69->80), 90 (nan at index 100), 120 (too short).
    assert len(data) == 2
    np.testing.assert_array_equal(data.x[1], x[30:61])
    mixed = datasets.concatenate([data, datasets.sample(
        datasets.SamplingConfig(trajectories=10))[0]])
    assert len(mixed) >= 2 + 9 and [p['source'] for p in mixed.provenance] == ['b', 'sampled']
