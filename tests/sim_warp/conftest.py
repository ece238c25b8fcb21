"""Fixtures of the MuJoCo Warp backend tests: Warp's CPU device, a few worlds, and one env for the session.

Warp compiles its kernels on first use (about 40 s cold on a 2-core machine; Warp keeps them in its kernel cache
for later runs) and keeps the compiled modules for the rest of the process, so the tests share one env where
they can. Tests marked `gpu` need CUDA and are skipped without it (tests/conftest.py; `make test-gpu`).
"""

from __future__ import annotations

import pytest

pytest.importorskip("mujoco_warp", reason="the warp backend needs the [warp] extra: pip install -e '.[warp]'")

from envs.config import EnvConfig  # noqa: E402
from rotation.sim_warp.core import RotateCupWarp, WarpConfig  # noqa: E402

NUM_WORLDS = 3
SEED = 7
HAND = "digit360"
"""The hand the warp backend simulates: it refuses the digit360_v4 hand's physics (rotation.sim_warp.core)."""


@pytest.fixture(scope="session")
def warp_env():
    """RotateCup on Warp's CPU device with NUM_WORLDS worlds (the randomized task on HAND); tests reset it."""
    env = RotateCupWarp(EnvConfig(hand=HAND), num_envs=NUM_WORLDS, seed=SEED, warp_cfg=WarpConfig(device="cpu"))
    yield env
    env.close()
