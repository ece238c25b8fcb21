"""`rotate evaluate --touch-delay`: a tactile adapter's correction acts some control steps after the touch it read,
and the next refresh waits for it, as in `rotate deploy` (rotation.deploy.touch); the delay line of
adapters.touch_delay."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from adapters.touch_delay import MEASURED, DelayLine, delay_spec, parse_delay
from envs.config import EnvConfig
from envs.core import RotateCupVec
from rotation.evaluate import finished, job, rollout

LATENT = 3


class FakeAdapter:
    """Stands in for adapters.bundle.AdaptedPolicy: records the correction each step acts with."""

    def __init__(self, touch_every: int, touch_smoothing: float = 0.0) -> None:
        self.touch_every, self.touch_smoothing = touch_every, touch_smoothing
        self.env_needs: dict = {}
        self.config = SimpleNamespace(latent_dim=LATENT, obs_groups=("proprio",))
        self.acted: list[float] = []  # env 0's correction, one per step
        self.requested: list[int] = []  # the step of each refresh

    def start_correction(self, step):
        return None  # no cautious start

    def act_batch(self, groups, correction):
        self.acted.append(float(correction[0, 0]))
        return np.zeros((len(correction), 16), dtype=np.float32)


@pytest.fixture(scope="module")
def env():
    vec = RotateCupVec(EnvConfig(episode_steps=12), num_envs=1, seed=0, nthread=1)
    yield vec
    vec.close()


def _run(env, monkeypatch, every: int, lag: int | str, smoothing: float = 0.0) -> FakeAdapter:
    policy = FakeAdapter(every, smoothing)

    def correction(bundle, obs, groups, idx=None):  # refresh r (from 1) reads step `len(acted)`
        bundle.requested.append(len(bundle.acted))
        return np.full((len(idx), LATENT), float(len(bundle.requested)), dtype=np.float32)

    monkeypatch.setattr(rollout, "touch_correction", correction)
    rollout.run_episodes(policy, env, 1, 0, touch_delay=parse_delay(str(lag)))
    return policy


@pytest.mark.parametrize(("every", "lag", "requested", "acted"), [
    # no delay: each refresh acts on the step it read, every `every` steps
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


@pytest.mark.parametrize(("lag", "acted"), [
    # refreshes read 1, 2, 3: the first is taken as it is, each next one keeps half of the held correction
    (0, [1, 1, 1, 1, 1.5, 1.5, 1.5, 1.5, 2.25, 2.25, 2.25, 2.25]),
    # landing late changes when, not what: the student alone until the first lands
    (2, [0, 0, 1, 1, 1, 1, 1.5, 1.5, 1.5, 1.5, 2.25, 2.25]),
])
def test_a_smoothing_bundle_averages_its_corrections_over_refreshes(env, monkeypatch, lag, acted):
    policy = _run(env, monkeypatch, 4, lag, smoothing=0.5)
    assert len(policy.acted) == 12
    assert policy.requested == [0, 4, 8]
    assert policy.acted == pytest.approx(acted)


def test_a_restarted_episode_takes_its_first_correction_as_it_is():
    line = DelayLine(2, LATENT, 1, parse_delay("0"), [1, 2], smoothing=0.9)
    value = iter(range(1, 100))
    fresh = lambda ids: np.full((len(ids), LATENT), float(next(value)), np.float32)  # noqa: E731
    assert line.step(0, np.arange(2), fresh)[:, 0].tolist() == [1, 1]  # one call for both envs: both read 1
    assert line.step(1, np.arange(2), fresh)[:, 0] == pytest.approx([1.1, 1.1])  # 0.9 * 1 + 0.1 * 2
    line.restart(np.array([1]), 2)
    assert line.step(2, np.arange(2), fresh)[:, 0] == pytest.approx([0.9 * 1.1 + 0.3, 3.0])


@pytest.mark.parametrize("bad", [1.0, -0.1, True, "0.5", float("nan")])
def test_touch_smoothing_is_checked(bad):
    with pytest.raises(ValueError, match=r"touch_smoothing must be a number in \[0, 1\)"):
        DelayLine(1, LATENT, 1, parse_delay("0"), [0], smoothing=bad)


def test_a_drawn_delay_acts_exactly_the_touch_of_that_many_steps_before(env, monkeypatch):
    """Every step acts with the newest correction that has landed, and each landed exactly its drawn delay after
    the step whose touch it read: a correction read at step r acts first at r + d, with d one of the spec's."""
    policy = _run(env, monkeypatch, 1, "1:0.5,3:0.5")
    assert len(policy.acted) == 12
    reads = policy.requested  # refresh r (1-based) read step reads[r - 1]
    landed = {}  # refresh -> first step acting with it
    for step, value in enumerate(policy.acted):
        if value and int(value) not in landed:
            landed[int(value)] = step
    delays = [landed[r] - reads[r - 1] for r in landed]
    assert set(delays) <= {1, 3} and len(set(delays)) == 2, delays
    # a refresh starts only once the previous one landed: the next read is the step the previous one acted first
    assert all(reads[r] == landed[r] for r in landed if r < len(reads))


def test_the_delay_line_draws_per_env_streams_independent_of_the_batch():
    delay = parse_delay("0:0.3,1:0.3,4:0.4")
    calls = []

    def fresh(ids):
        calls.append(ids.tolist())
        return np.ones((len(ids), LATENT), np.float32)

    def schedule(seeds, env):
        line = DelayLine(len(seeds), LATENT, 1, delay, seeds)
        return [int(line.step(k, np.arange(len(seeds)), fresh)[env, 0] != 0 and line.read_step[env])
                for k in range(30)]

    alone = schedule([7], 0)
    beside = schedule([3, 7, 11], 1)
    assert alone == beside


@pytest.mark.parametrize("text", ["-1", "2.5", "x", "1:0.5,3", "101", "1:0,2:0", "1:nan"])
def test_touch_delay_is_checked(text):
    with pytest.raises(ValueError, match="touch_delay"):
        job.Config(touch_delay=text, progress=False)


def test_delays_parse_and_describe():
    assert parse_delay("0").is_zero
    d = parse_delay("2:1,3:3")
    assert d.steps == (2, 3) and d.probs == (0.25, 0.75) and d.mean == pytest.approx(2.75)
    assert "2 steps (25%), 3 steps (75%)" in d.describe()
    assert parse_delay("measured") is MEASURED
    assert delay_spec(parse_delay("3:1,1:1")) == "1:0.500,3:0.500"


def test_an_evaluation_recorded_before_touch_delay_existed_continues_only_without_delay(tmp_path):
    """Recorded before the field existed means no delay: at '0' the field is not part of an evaluation's identity;
    any other delay is, as the distribution it stands for (so 'measured' re-measured is a different evaluation)."""
    plain = finished.identity(job.Config(policies={"student": "student"}, out=tmp_path / "a", touch_delay="0"), {})
    assert "touch_delay" not in plain["config"]
    measured = finished.identity(job.Config(policies={"student": "student"}, out=tmp_path / "a"), {})
    assert measured["config"]["touch_delay"] == delay_spec(MEASURED)
    assert {k: v for k, v in measured["config"].items() if k != "touch_delay"} == plain["config"]
    # an evaluation of policies that read no touch does not depend on the delay
    untouched = finished.identity(job.Config(policies={"student": "student"}, out=tmp_path / "a"), {},
                                  reads_touch=False)
    assert untouched == plain
