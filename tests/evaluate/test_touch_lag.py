"""`rotate evaluate --touch-lag`: a tactile adapter's correction acts some control steps after the touch it read,
and the next refresh waits for it, as in `rotate deploy` (rotation.deploy.touch)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from envs.config import EnvConfig
from envs.core import RotateCupVec
from rotation.evaluate import finished, job, rollout

LATENT = 3


class FakeAdapter:
    """Stands in for adapters.bundle.AdaptedPolicy: records the correction each step acts with."""

    def __init__(self, touch_every: int) -> None:
        self.touch_every = touch_every
        self.env_needs: dict = {}
        self.config = SimpleNamespace(latent_dim=LATENT, obs_groups=("proprio",))
        self.acted: list[float] = []  # env 0's correction, one per step
        self.requested: list[int] = []  # the step of each refresh

    def act_batch(self, groups, correction):
        self.acted.append(float(correction[0, 0]))
        return np.zeros((len(correction), 16), dtype=np.float32)


@pytest.fixture(scope="module")
def env():
    vec = RotateCupVec(EnvConfig(episode_steps=12), num_envs=1, seed=0, nthread=1)
    yield vec
    vec.close()


def _run(env, monkeypatch, every: int, lag: int) -> FakeAdapter:
    policy = FakeAdapter(every)

    def correction(bundle, obs, groups, idx=None):  # refresh r (from 1) reads step `len(acted)`
        bundle.requested.append(len(bundle.acted))
        return np.full((len(idx), LATENT), float(len(bundle.requested)), dtype=np.float32)

    monkeypatch.setattr(rollout, "touch_correction", correction)
    rollout.run_episodes(policy, env, 1, 0, touch_lag=lag)
    return policy


@pytest.mark.parametrize(("every", "lag", "requested", "acted"), [
    # no lag: each refresh acts on the step it read, every `every` steps (the behaviour before --touch-lag)
    (4, 0, [0, 4, 8], [1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3]),
    # a refresh shorter than the period: it lands 2 steps late; the student (zero correction) acts until then
    (4, 2, [0, 4, 8], [0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3]),
    # a refresh longer than the period: refreshes run back to back, each when the previous one lands
    (2, 3, [0, 3, 6, 9], [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3]),
])
def test_a_lagged_refresh_acts_later_and_the_next_one_waits_for_it(env, monkeypatch, every, lag, requested, acted):
    policy = _run(env, monkeypatch, every, lag)
    assert len(policy.acted) == 12, "the cup fell: the schedule below assumes the whole 12-step episode"
    assert policy.requested == requested
    assert policy.acted == acted


def test_touch_lag_is_checked():
    with pytest.raises(ValueError, match="touch_lag"):
        job.Config(touch_lag=-1, progress=False)
    with pytest.raises(ValueError, match="touch_lag"):
        job.Config(touch_lag=2.5, progress=False)


def test_an_evaluation_recorded_before_touch_lag_existed_still_continues(tmp_path):
    """At its default the new field is not part of an evaluation's identity; set, it is (and refuses a mix)."""
    plain = finished.identity(job.Config(policies={"student": "student"}, out=tmp_path / "a"), {})
    assert "touch_lag" not in plain["config"]
    lagged = finished.identity(job.Config(policies={"student": "student"}, out=tmp_path / "a", touch_lag=2), {})
    assert lagged["config"]["touch_lag"] == 2
    assert {k: v for k, v in lagged["config"].items() if k != "touch_lag"} == plain["config"]
