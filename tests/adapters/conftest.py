"""Fixtures shared by the adapter tests."""

from __future__ import annotations

import pytest

from envs.config import EnvConfig
from envs.core import RotateCupVec
from rotation.bundles import load_bundle


@pytest.fixture(scope="module")
def env_obs():
    """A touch-enabled env after a few steps of the shipped student (fingertips in contact)."""
    student = load_bundle("student")
    env = RotateCupVec(EnvConfig(tactile=True), num_envs=2, seed=5, nthread=1)
    obs = env.reset(seed=5)
    for _ in range(12):
        obs, *_ = env.step(student.act_batch({k: obs[k] for k in student.config.obs_groups}))
    yield env, obs
    env.close()
