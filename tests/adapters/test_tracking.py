"""An adapter that also reads the joints' tracking over the proprioceptive history (``--tracking``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adapters.bundle import build_adapted, load_adapter
from adapters.finetune import core
from adapters.finetune import job as finetune
from adapters.finetune.sim import tracking_norm
from adapters.model import TRACKING_DIM, tracking_features
from envs.constants import JOINT_LOWER, JOINT_UPPER, scale_joints
from rotation.bundles import load_bundle

ENCODER = "sparshx-tinier-sim"


def _windows(policy, obs):
    return {f: {w: obs["tactile"][f][w] for w in policy.windows} for f in policy.fingers}


def _tiny_cfg(out, **kw) -> finetune.Config:
    base = dict(out=out, modalities="pressure", total_steps=256, num_envs=2, touch_every=2, student_steps=64,
                updates=16, batch_size=32, buffer_size=512, lr=1e-3, checkpoint_every=128, log_every=8,
                progress=False, torch_threads=1, nthread=1, seed=0, tracking=True)
    return finetune.Config(**{**base, **kw})


def test_tracking_features_are_each_joints_mean_error_its_spread_and_its_mean_position():
    rng = np.random.default_rng(0)
    q = rng.uniform(JOINT_LOWER, JOINT_UPPER, size=(3, 30, 16))  # rad
    target = q + rng.normal(0.0, 0.05, size=q.shape) + 0.02
    hist = np.concatenate([scale_joints(q), target], axis=-1).astype(np.float64)
    got = tracking_features(torch.as_tensor(hist)).numpy()
    err = target - q
    want = np.concatenate([err.mean(1), err.std(1), q.mean(1)], axis=-1)
    assert got.shape == (3, TRACKING_DIM)
    np.testing.assert_allclose(got, want, atol=1e-9)
    with pytest.raises(ValueError, match="history"):
        tracking_features(torch.zeros(3, 30, 16))


def test_a_tracking_adapter_starts_as_the_student_and_refuses_a_missing_history(env_obs):
    env, obs = env_obs
    policy = build_adapted("student", ENCODER, ("pressure",), seed=3, tracking=True)
    groups = {k: obs[k] for k in policy.config.obs_groups}
    assert policy.tracking(groups).shape == (2, TRACKING_DIM)
    corr = policy.correction(_windows(policy, obs), groups)
    assert np.all(corr == 0.0)
    student = load_bundle("student")
    assert np.array_equal(policy.act_batch(groups, correction=corr), student.act_batch(groups))
    pooled = policy.adapter.pooled(policy.tokens(_windows(policy, obs)))
    z = policy.student_latent(groups)
    with pytest.raises(ValueError, match="joint tracking"):
        policy.adapter.hidden(pooled, z)
    with pytest.raises(ValueError, match="joint tracking"):
        policy.adapter.hidden(pooled, z, torch.zeros(2, 5))
    with pytest.raises(ValueError, match="statistics"):
        policy.adapter.set_tracking_norm(torch.zeros(3), torch.ones(3))
    plain = build_adapted("student", ENCODER, ("pressure",), seed=3)
    assert plain.tracking(groups).shape == (2, 0)
    with pytest.raises(ValueError, match="reads no joint tracking"):
        plain.adapter.set_tracking_norm(torch.zeros(TRACKING_DIM), torch.ones(TRACKING_DIM))


def test_init_from_an_adapter_without_tracking_starts_with_its_corrections(env_obs, tmp_path):
    """Zero weights on the new features: the same corrections whatever the joints do, and the normalization is
    left to be measured."""
    env, obs = env_obs
    plain = build_adapted("student", ENCODER, ("pressure",), seed=3)
    torch.manual_seed(1)
    for p in plain.adapter.parameters():
        torch.nn.init.normal_(p, std=0.1)
    plain.save(tmp_path / "plain")
    job = core.Job.start_from(_tiny_cfg(tmp_path / "run", init_from=str(tmp_path / "plain")))
    assert job.tracking_norm_needed
    groups = {k: obs[k] for k in plain.config.obs_groups}
    want = plain.correction(_windows(plain, obs), groups)
    assert np.abs(want).max() > 1e-3
    padded = job.policy
    np.testing.assert_allclose(padded.correction(_windows(padded, obs), groups), want, atol=1e-6)
    padded.adapter.set_tracking_norm(torch.randn(TRACKING_DIM), torch.rand(TRACKING_DIM) + 0.1)
    np.testing.assert_allclose(padded.correction(_windows(padded, obs), groups), want, atol=1e-6)
    with pytest.raises(ValueError, match="init_from"):  # another network is still refused
        core.Job.start_from(_tiny_cfg(tmp_path / "other", hidden=(32,), init_from=str(tmp_path / "plain")))


@pytest.fixture(scope="module")
def tracking_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("tracking") / "run"
    return out, finetune.run(_tiny_cfg(out))


def test_a_tracking_run_measures_its_normalization_and_learns_from_the_joints(tracking_run):
    out, result = tracking_run
    policy = load_adapter(result.bundle_dir)
    adapter = policy.adapter
    assert adapter.cfg.tracking and policy.adapter_config.card["config"]["tracking"] is True
    mean, std = tracking_norm(policy, _tiny_cfg(out))  # the student's rollouts in the training env
    torch.testing.assert_close(adapter.track_mean, mean)
    torch.testing.assert_close(adapter.track_std, std.clamp_min(1e-4))
    assert 0.001 < float(std[:16].median()) < 0.2  # tracking errors of a few hundredths of a radian
    first = adapter.g[0].weight
    assert float(first[:, -TRACKING_DIM:].detach().abs().sum()) > 0  # the features reach g and are learned
    hist = result.history
    late = hist[len(hist) // 2:]
    adapted = np.mean([h["latent_mse"] for h in late])
    student = np.mean([h["student_mse"] for h in late])
    assert adapted < 0.8 * student, (adapted, student)


def test_a_tracking_run_resumes_exactly(tracking_run, tmp_path):
    out, result = tracking_run
    part = tmp_path / "part"
    finetune.run(_tiny_cfg(part, total_steps=128))
    resumed = finetune.run(_tiny_cfg(part, total_steps=256, resume=True))
    a, b = load_adapter(result.bundle_dir), load_adapter(resumed.bundle_dir)
    for (name, x), y in zip(a.adapter.state_dict().items(), b.adapter.state_dict().values(), strict=True):
        assert torch.equal(x, y), name
