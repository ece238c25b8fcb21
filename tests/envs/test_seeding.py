"""Gymnasium's seeding convention: fresh envs draw fresh entropy, seeded resets reproduce, bad seeds are refused."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from envs import EnvConfig, RotateCupVec
from envs.rotate_cup import RotateCupEnv
from envs.vector import RotateCupVectorEnv


def _priv(obs) -> np.ndarray:
    return np.asarray(obs["priv"])  # position, scale, mass, friction, CoM: differ between randomized episodes


def test_fresh_envs_reset_without_a_seed_differ():
    a, _ = RotateCupEnv().reset()
    b, _ = RotateCupEnv().reset()
    assert not np.array_equal(_priv(a), _priv(b))


def test_a_sync_vector_env_of_copies_is_not_n_identical_envs():
    venv = gym.vector.SyncVectorEnv([RotateCupEnv for _ in range(3)])
    obs, _ = venv.reset()
    assert len({tuple(p) for p in obs["priv"]}) == 3
    # seeded, the copies are env i of a batch seeded s (gymnasium gives copy i the seed s + i)
    obs, _ = venv.reset(seed=11)
    batch = RotateCupVec(EnvConfig(), num_envs=3, seed=0, nthread=1).reset(seed=11)
    np.testing.assert_array_equal(obs["priv"], batch["priv"])
    venv.close()


def test_fresh_vector_env_draws_fresh_entropy_and_seeded_resets_reproduce():
    first, _ = RotateCupVectorEnv(2).reset()
    second, _ = RotateCupVectorEnv(2).reset()
    assert not np.array_equal(first["priv"], second["priv"])
    a, _ = RotateCupVectorEnv(2).reset(seed=4)
    b, _ = RotateCupVectorEnv(2).reset(seed=4)
    np.testing.assert_array_equal(a["priv"], b["priv"])


def test_unseeded_resets_after_a_seeded_one_continue_its_stream():
    a, b = RotateCupEnv(), RotateCupEnv()
    a.reset(seed=3)
    b.reset(seed=3)
    np.testing.assert_array_equal(_priv(a.reset()[0]), _priv(b.reset()[0]))


@pytest.mark.parametrize("seed", [0, 7, np.int64(7), 2**63 - 1, 2**63, 2**64 - 1])
def test_every_64_bit_seed_works(seed):
    obs, _ = RotateCupEnv().reset(seed=seed)
    again, _ = RotateCupEnv().reset(seed=int(seed))
    np.testing.assert_array_equal(_priv(obs), _priv(again))


def test_a_batch_seeded_near_the_top_wraps_like_single_envs():
    """Env i of a batch seeded s is the single env seeded (s + i) mod 2**64, also across 2**63 (int64 overflowed)."""
    batch = RotateCupVec(EnvConfig(), num_envs=3, seed=0, nthread=1).reset(seed=2**64 - 2)
    for i, seed in enumerate((2**64 - 2, 2**64 - 1, 0)):
        np.testing.assert_array_equal(batch["priv"][i], _priv(RotateCupEnv().reset(seed=seed)[0]))
    near = RotateCupVec(EnvConfig(), num_envs=2, seed=2**63 - 1, nthread=1).reset()
    np.testing.assert_array_equal(near["priv"][1], _priv(RotateCupEnv().reset(seed=2**63)[0]))


@pytest.mark.parametrize("seed", [-1, 2**64, 1.0, "3", True])
def test_other_seeds_are_refused_clearly(seed):
    message = r"seed must be an integer in \[0, 18446744073709551615\], got "
    with pytest.raises(ValueError, match=message):
        RotateCupEnv().reset(seed=seed)
    with pytest.raises(ValueError, match=message):
        RotateCupVectorEnv(2).reset(seed=seed)
    with pytest.raises(ValueError, match=message):
        RotateCupVec(EnvConfig(), num_envs=1, seed=seed)
    with pytest.raises(ValueError, match=message):
        RotateCupVec(EnvConfig(), num_envs=1).reset(seed=seed)
