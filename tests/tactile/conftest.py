"""Fixtures for the touch-encoder tests: a few short simulated sessions (random policy, touch on) and their
window cache, made once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from rotation.data.window_cache import build_cache
from rotation.jobs import collect

CACHE_STRIDE = 3
"""Window stride of the cached fixture (10 windows per second and fingertip)."""


@pytest.fixture(scope="session")
def cache_stride() -> int:
    """The window stride ``touch_cache`` was built with: tests that read it again pass the same stride."""
    return CACHE_STRIDE


@pytest.fixture(scope="session")
def touch_sessions(tmp_path_factory) -> Path:
    """4 sessions of 2.3 s (a gentle random policy that keeps the cup): about 36 window ends per fingertip."""
    out = tmp_path_factory.mktemp("touch_sessions")
    collect.run(collect.Config(out=out, episodes=4, num_envs=4, episode_steps=46, seed=5, random_scale=0.15,
                               progress=False))
    return out


@pytest.fixture(scope="session")
def touch_cache(touch_sessions, tmp_path_factory) -> Path:
    """The sessions' windows at stride 3, pre-rendered (about 48 per session)."""
    out = tmp_path_factory.mktemp("touch_cache")
    build_cache([touch_sessions], out, stride=CACHE_STRIDE, progress=False)
    return out
