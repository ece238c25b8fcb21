"""`rotate finetune-adapter --refit-head`: the zero layer solved by ridge regression on the adapter's own rollouts,
with the ridge strength chosen by cross-validation over whole episodes; every other weight kept."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from adapters.bundle import load_adapter
from adapters.finetune import job as finetune
from adapters.finetune.refit import ridge, ridge_by_episode_cv
from envs.config import EnvConfig


def test_ridge_recovers_a_linear_map():
    rng = np.random.default_rng(0)
    h = rng.normal(size=(400, 6)) + 3.0  # features off centre: the bias must absorb the mean
    w = rng.normal(size=(6, 2))
    t = h @ w + np.array([0.5, -1.0]) + 0.01 * rng.normal(size=(400, 2))
    weight, bias = ridge(h, t, 1e-8)
    np.testing.assert_allclose(weight, w, atol=5e-3)
    np.testing.assert_allclose(bias, [0.5, -1.0], atol=3e-2)
    shrunk, _ = ridge(h, t, 10.0)
    assert np.abs(shrunk).sum() < 0.5 * np.abs(weight).sum()  # the penalty shrinks the weights


def test_cross_validation_holds_out_whole_episodes():
    """Each episode has its own offset that the features do not explain, and within an episode the features are
    nearly constant: a weak penalty fits the offsets through the features, which only episodes held out whole show.
    The chosen strength must be the stronger one; with samples held out at random it would be the weakest."""
    rng = np.random.default_rng(1)
    episodes = np.repeat(np.arange(40), 25)
    per_episode = rng.normal(size=(40, 30))
    h = per_episode[episodes] + 0.01 * rng.normal(size=(1000, 30))
    t = (rng.normal(size=40)[episodes] + 0.01 * rng.normal(size=1000))[:, None]  # unrelated to h
    weight, bias, table, lam = ridge_by_episode_cv(h, t, episodes, (1e-6, 1e-3, 1.0, 100.0), folds=4)
    assert [r["lambda"] for r in table] == [1e-6, 1e-3, 1.0, 100.0]
    assert lam >= 1.0
    assert table[0]["cv_latent_mse"] > 1.2 * min(r["cv_latent_mse"] for r in table)
    *_, by_sample = ridge_by_episode_cv(h, t, np.arange(1000), (1e-6, 1e-3, 1.0, 100.0), folds=4)
    assert by_sample == 1e-6  # every sample its own "episode": the split that the episode ids exist to avoid
    with pytest.raises(ValueError, match="3 episodes collected"):
        ridge_by_episode_cv(h[:75], t[:75], episodes[:75], (1.0,), folds=4)


def _tiny(out, **kw) -> finetune.Config:
    base = dict(out=out, modalities="pressure", total_steps=192, num_envs=2, touch_every=2, updates=4,
                batch_size=16, buffer_size=256, checkpoint_every=96, log_every=8, progress=False, torch_threads=1,
                nthread=1, seed=0, env=EnvConfig(tactile=True, episode_steps=24), touch_delay="0")
    return finetune.Config(**{**base, **kw})


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny adapter trained with Adam: the one the refit starts from."""
    return finetune.run(_tiny(tmp_path_factory.mktemp("refit") / "adam")).bundle_dir


def test_refit_replaces_only_the_zero_layer_and_lowers_its_error(trained, tmp_path):
    result = finetune.run(_tiny(tmp_path / "refit", init_from=str(trained), refit_head=True, refit_folds=2,
                                refit_lambdas=(1e-4, 1e-2), seed=3))
    before, after = load_adapter(trained).adapter.state_dict(), load_adapter(result.bundle_dir).adapter.state_dict()
    for name, value in after.items():
        assert torch.equal(value, before[name]) != name.startswith("zero."), name
    card = load_adapter(result.bundle_dir).adapter_config.card
    refit = card["refit_head"]
    assert refit["lambda"] in (1e-4, 1e-2) and len(refit["cv"]) == 2
    # 96 iterations of 2 envs with a refresh every 2 (no delay: each lands at once), in 24-step episodes
    assert refit["samples"] == 96 and refit["episodes"] >= 8
    # the least-squares fit of the layer on its own samples beats the Adam-trained layer on the same samples
    assert refit["fit_latent_mse"] < refit["latent_mse_before"]
    assert card["config"]["refit_head"] is True
    rows = [json.loads(line) for line in (tmp_path / "refit" / "curves.jsonl").read_text().splitlines()]
    assert rows and all("latent_mse" in r for r in rows)


def test_refit_options_are_checked(tmp_path):
    with pytest.raises(ValueError, match="--init-from"):
        _tiny(tmp_path / "a", refit_head=True)
    with pytest.raises(ValueError, match="takes no --anchor, --action-weight"):
        _tiny(tmp_path / "b", refit_head=True, init_from="adapter", anchor="adapter", action_weight=1.0)
    with pytest.raises(ValueError, match="refit_lambdas must be numbers"):
        _tiny(tmp_path / "c", refit_head=True, init_from="adapter", refit_lambdas=(0.0,))
    with pytest.raises(ValueError, match="refit_folds"):
        _tiny(tmp_path / "d", refit_head=True, init_from="adapter", refit_folds=1)


@pytest.mark.parametrize(("stop_at", "refit"), [(60, True), (3, False)])
def test_a_stopped_refit_saves_what_it_has_and_says_so(trained, tmp_path, monkeypatch, stop_at, refit):
    """Ctrl-C mid-rollout: the layer is refit on the samples so far (or kept, with too few episodes for the folds),
    the bundle is saved and the stop is reported as an interruption with no --resume to offer."""
    from adapters.finetune import refit as refit_head
    from rotation.interrupt import Interrupted

    step = refit_head.EpisodeTracker.step
    calls = {"n": 0}

    def interrupted_step(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == stop_at:
            raise KeyboardInterrupt
        return step(self, *args, **kwargs)

    monkeypatch.setattr(refit_head.EpisodeTracker, "step", interrupted_step)
    cfg = _tiny(tmp_path / "stopped", init_from=str(trained), refit_head=True, refit_folds=4)
    with pytest.raises(Interrupted, match="interrupted by SIGINT .*run it again in full") as err:
        finetune.run(cfg)
    assert err.value.exit_code == 130
    assert ("refit on the samples collected" in str(err.value)) == refit
    card = load_adapter(tmp_path / "stopped" / "bundle").adapter_config.card
    assert "SIGINT" in card["interrupted"]
    assert (card["refit_head"] is not None) == refit
    before, after = load_adapter(trained).adapter.zero.weight, load_adapter(tmp_path / "stopped" / "bundle").adapter
    assert torch.equal(after.zero.weight, before) != refit
