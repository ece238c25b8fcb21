"""A skin adapter: the same adapter over a Sparsh-skin encoder, one sample for the whole Xela hand (the env's `skin`
group), exactly the student at initialization, fine-tuned and evaluated in simulation on the Xela hand, refused by
deploy (which reads Digit 360 fingertips only) and by a mixed evaluation. The encoder here is a fresh (untrained)
tinier Sparsh-skin saved to a file: the adapter path is what is tested, not what a pretrained encoder knows."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adapters.bundle import build_adapted, load_adapter
from adapters.bundle_config import SKIN_SAMPLE
from adapters.finetune import job as finetune
from envs.config import EnvConfig
from envs.core import RotateCupVec
from rotation.bundles import load_bundle
from rotation.deploy.touch import touch_sensors
from rotation.evaluate import job
from rotation.policy.bundle import BundleConfig, PolicyBundle
from rotation.tactile.models.sparsh_skin import SparshSkin, SparshSkinConfig, save_skin


@pytest.fixture(scope="module")
def skin_encoder(tmp_path_factory) -> str:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("skin") / "enc.safetensors"
    return str(save_skin(SparshSkin(SparshSkinConfig(size="tinier")), path))


@pytest.fixture(scope="module")
def student(tmp_path_factory) -> str:
    """A student with random weights and no sim record, so of the first hand model: it acts on 'digit360' and on
    its Xela twin 'xela', the hand a skin adapter reads. (The shipped student trained on the vendor-kinematics hand;
    a skin adapter of it needs a teacher trained on 'xela_v4' first.) The adapter's path is what is tested."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("student") / "student"
    return str(PolicyBundle(BundleConfig(latent_source="adaptation")).save(path))


@pytest.fixture(scope="module")
def xela_obs(student):
    """The Xela hand with its skin after a few steps of the student."""
    student = load_bundle(student)
    env = RotateCupVec(EnvConfig(hand="xela", skin=True), num_envs=2, seed=3, nthread=1)
    obs = env.reset(seed=3)
    for _ in range(6):
        obs, *_ = env.step(student.act_batch({k: obs[k] for k in student.config.obs_groups}))
    yield obs
    env.close()


def test_a_fresh_skin_adapter_reads_the_hand_and_acts_exactly_like_the_student(skin_encoder, xela_obs, student):
    policy = build_adapted(student, skin_encoder, ("skin",), touch_every=2)
    assert policy.sensor == "skin" and policy.fingers == (SKIN_SAMPLE,) and policy.windows == ("skin",)
    assert policy.env_needs == {"hand": "xela", "skin": True}
    groups = {k: xela_obs[k] for k in policy.config.obs_groups}
    windows = policy.env_windows(xela_obs)
    assert windows[SKIN_SAMPLE]["skin"].shape == (2, 10, 368, 6)
    tokens = policy.tokens(windows)
    assert tokens[SKIN_SAMPLE]["skin"].shape == (2, 368, 96)
    corr = policy.correction(windows, groups)
    assert corr.shape == (2, policy.config.latent_dim) and np.all(corr == 0.0)  # ZeroLinear: exactly zero
    np.testing.assert_array_equal(policy.act_batch(groups, correction=corr), policy.student.act_batch(groups))
    one = policy.env_windows(xela_obs, np.array([1]))[SKIN_SAMPLE]["skin"]
    np.testing.assert_array_equal(one, xela_obs["skin"][[1]])


def test_skin_adapter_finetunes_on_the_xela_hand_and_evaluates_beside_the_student(skin_encoder, tmp_path, student):
    cfg = finetune.Config(out=tmp_path / "run", student=student, encoder=skin_encoder, modalities="skin",
                          total_steps=96, num_envs=2, touch_every=2, student_steps=32, updates=16, batch_size=32,
                          buffer_size=256, lr=1e-3, checkpoint_every=96, log_every=4, progress=False, torch_threads=1,
                          nthread=1, seed=0)
    assert (cfg.env.hand, cfg.env.skin, cfg.env.tactile) == ("xela", True, False)  # forced: the touch it reads
    result = finetune.run(cfg)
    assert result.history and all(np.isfinite(h["latent_mse"]) for h in result.history)
    policy = load_adapter(result.bundle_dir)
    assert policy.sensor == "skin" and policy.adapter_config.modalities == ("skin",)
    assert any(p.abs().sum() > 0 for p in policy.adapter.zero.parameters())  # it learned: no longer the zero map
    rows = job.run(job.Config(policies={"student": student, "skin_adapter": str(result.bundle_dir)}, episodes=2,
                              episode_steps=8, out=tmp_path / "eval", num_envs=2, nthread=1, progress=False, seed=7))
    assert [r["policy"] for r in rows] == ["student", "skin_adapter"]
    # the student's row ran on the Xela hand too: the same episodes as evaluating it there alone
    xela = job.Config(policies={"student": student}, episodes=2, episode_steps=8, out=tmp_path / "x", num_envs=2,
                      nthread=1, progress=False, seed=7)
    env = RotateCupVec(job.env_config(xela, load_bundle(student), job.resolve_conditions(xela)[0].perturb,
                                      {"hand": "xela", "skin": True}), num_envs=2, seed=7, nthread=1)
    from rotation.evaluate.rollout import run_episodes

    try:
        alone = run_episodes(load_bundle(student), env, 2, 7)
    finally:
        env.close()
    assert rows[0]["rotation_rate"] == pytest.approx(np.mean([e.rotation_rate for e in alone]), rel=1e-9)
    # a skin adapter and a Digit 360 adapter need different hands: refused before anything runs
    digit = build_adapted(student, "sparshx-tinier-sim", ("pressure",))
    digit.save(tmp_path / "digit")
    with pytest.raises(ValueError, match="separate runs"):
        job.run(job.Config(policies={"a": str(result.bundle_dir), "b": str(tmp_path / "digit")}, episodes=1,
                           out=tmp_path / "mixed", progress=False))
    # deploy reads Digit 360 fingertips only: a clear refusal before any sensor or motor starts
    with pytest.raises(ValueError, match="reads the Xela skin"):
        touch_sensors(policy, "skin_adapter", {}, emulated=True)
    # fine-tuning on recorded sessions trains Digit 360 adapters only: refused before training
    with pytest.raises(ValueError, match="simulation"):
        finetune.Config(out=tmp_path / "s", encoder=skin_encoder, modalities="skin", sessions=(tmp_path,))
