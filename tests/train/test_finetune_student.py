"""`rotate finetune-student`: PPO on a distilled student's actor, phi frozen, a privileged critic."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import EnvConfig
from envs.core import RotateCupVec
from rotation.bundles import load_bundle
from rotation.cli import main
from rotation.policy.bundle import resolve_bundle
from rotation.policy.features import (
    LATENT_MIX_GROUP,
    LatentMixExtractor,
    PrivilegedExtractor,
    StudentExtractor,
    StudentPPOPolicy,
)
from rotation.train import finetune_student, ppo, teacher, teacher_config, vec_env
from rotation.train.ppo import AdaptiveKLPPO


def _cfg(tmp_path, **kw) -> finetune_student.Config:
    base = dict(out=tmp_path / "run", num_envs=8, n_steps=16, batch_size=64, n_epochs=2, total_steps=512,
                checkpoint_every=256, episode_steps=40, progress=False, seed=0, critic_warmup=1)
    base.update(kw)
    return finetune_student.Config(**base)


def _weights(bundle) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in bundle.net.state_dict().items()}


def test_phi_stays_frozen_and_the_actor_learns(tmp_path):
    start = _weights(load_bundle("student"))
    cfg = _cfg(tmp_path)
    out = finetune_student.run(cfg)
    assert out.config.latent_source == "adaptation" and out.config.card["role"] == "student"
    assert out.config.card["finetuned_from"]["bundle"] == "student"
    after = _weights(load_bundle(cfg.out / "bundle"))
    frozen = [k for k in start if k.startswith(("extractor.adaptation.", "extractor.hist_norm."))]
    assert frozen and all(torch.equal(start[k], after[k]) for k in frozen)
    assert not torch.equal(start["actor.0.weight"], after["actor.0.weight"])
    assert not torch.equal(start["action_mean.weight"], after["action_mean.weight"])


def test_the_policy_is_asymmetric_and_starts_as_the_student(tmp_path):
    cfg = _cfg(tmp_path)
    env = vec_env.RotateCupSB3VecEnv(cfg.env_config(), cfg.num_envs, seed=0, obs_groups=teacher_config.obs_groups(cfg))
    try:
        model = ppo.build_model(cfg, env)
    finally:
        env.close()
    policy = model.policy
    assert isinstance(policy, StudentPPOPolicy)
    assert isinstance(policy.pi_features_extractor, StudentExtractor)
    assert isinstance(policy.vf_features_extractor, PrivilegedExtractor)
    assert not any(p.requires_grad for p in policy.pi_features_extractor.adaptation.parameters())
    # the deterministic actions of the fresh PPO policy are the student bundle's, bit for bit
    core = RotateCupVec(cfg.env_config(), num_envs=4, seed=5, nthread=1)
    obs = core.reset(seed=5)
    core.close()
    student = load_bundle("student")
    policy.set_training_mode(False)
    with torch.no_grad():
        mean = policy.get_distribution({k: torch.as_tensor(obs[k]) for k in teacher_config.STUDENT_RL_GROUPS}).mode()
    np.testing.assert_array_equal(mean.clamp(-1, 1).numpy(), student.act_batch(obs))


def test_critic_warmup_leaves_the_actor_alone(tmp_path):
    start = _weights(load_bundle("student"))
    cfg = _cfg(tmp_path, critic_warmup=100)  # more warm-up updates than the run has
    finetune_student.run(cfg)
    after = _weights(load_bundle(cfg.out / "bundle"))
    acting = [k for k in start if not k.startswith("extractor.proprio_norm.")]
    assert all(torch.equal(start[k], after[k]) for k in acting)


def test_resume_continues_a_student_run(tmp_path):
    cfg = _cfg(tmp_path)
    finetune_student.run(cfg)
    last = cfg.out / "checkpoints" / "last.zip"
    resumed = finetune_student.run(_cfg(tmp_path, total_steps=1024, resume=last))
    assert resumed.config.card["steps"] == 1024
    model = ppo.load_checkpoint(last)
    assert isinstance(model.policy, StudentPPOPolicy) and model.num_timesteps == 1024
    assert ppo.bundle_from_checkpoint(last).config.card["role"] == "student"


def test_bad_students_are_refused(tmp_path):
    with pytest.raises(ValueError, match="not a student bundle"):
        _cfg(tmp_path, student="teacher")
    with pytest.raises(ValueError, match="student: "):
        _cfg(tmp_path, student=str(tmp_path / "nowhere"))
    with pytest.raises(ValueError, match="neither --init-from"):
        teacher.Config(out=tmp_path / "x", student="student", init_from=resolve_bundle("teacher"))
    with pytest.raises(ValueError, match="net_arch"):
        cfg = _cfg(tmp_path, net_arch=(64, 64))
        env = vec_env.RotateCupSB3VecEnv(cfg.env_config(), 2, obs_groups=teacher_config.obs_groups(cfg))
        try:
            ppo.build_model(cfg, env)
        finally:
            env.close()


def test_cli_refuses_a_teacher_as_student(tmp_path, capsys):
    code = main(["finetune-student", "--student", "teacher", "--out", str(tmp_path / "run")])
    assert code == 2
    assert "not a student bundle" in capsys.readouterr().err


def test_a_finetuned_checkpoint_loads_as_ppo(tmp_path):
    cfg = _cfg(tmp_path)
    finetune_student.run(cfg)
    model = AdaptiveKLPPO.load(cfg.out / "checkpoints" / "last.zip", device="cpu")
    assert isinstance(model.policy.vf_features_extractor, PrivilegedExtractor)


# --------------------------------------------------------------------------------------------------------------------
# --latent-mix: the actor also meets latents moved toward the teacher's z


def _mix_model(cfg):
    env = vec_env.RotateCupSB3VecEnv(cfg.env_config(), cfg.num_envs, seed=0, obs_groups=teacher_config.obs_groups(cfg),
                                     latent_mix=cfg.latent_mix)
    try:
        return ppo.build_model(cfg, env), env.observation_space
    finally:
        env.close()


def test_latent_mix_blends_phi_and_the_teachers_z(tmp_path):
    cfg = _cfg(tmp_path, latent_mix=0.5)
    model, space = _mix_model(cfg)
    extractor = model.policy.pi_features_extractor
    assert isinstance(extractor, LatentMixExtractor) and LATENT_MIX_GROUP in space.spaces
    assert not any(p.requires_grad for p in extractor.teacher_encoder.parameters())
    core = RotateCupVec(cfg.env_config(), num_envs=3, seed=7, nthread=1)
    obs = core.reset(seed=7)
    core.close()
    phi = load_bundle("student").latent(obs)
    z_teacher = load_bundle("teacher").latent(obs)
    tensors = {k: torch.as_tensor(obs[k]) for k in teacher_config.STUDENT_RL_GROUPS}
    w = torch.tensor([[0.0], [1.0], [0.25]])
    with torch.no_grad():
        z = extractor.z(tensors | {LATENT_MIX_GROUP: w}).numpy()
    np.testing.assert_allclose(z[0], phi[0], atol=1e-6)  # weight 0: the student's own latent
    np.testing.assert_allclose(z[1], z_teacher[1], atol=1e-6)  # weight 1: the teacher's
    np.testing.assert_allclose(z[2], phi[2] + 0.25 * (z_teacher[2] - phi[2]), atol=1e-6)


def test_latent_mix_run_gives_a_plain_student_bundle(tmp_path):
    start = _weights(load_bundle("student"))
    cfg = _cfg(tmp_path, latent_mix=0.5)
    out = finetune_student.run(cfg)
    bundle = load_bundle(cfg.out / "bundle")  # the teacher's encoder stays in the checkpoint, not the bundle
    assert out.config.latent_source == "adaptation" and set(_weights(bundle)) == set(start)
    assert out.config.card["train_config"]["latent_mix"] == 0.5
    frozen = [k for k in start if k.startswith(("extractor.adaptation.", "extractor.hist_norm."))]
    assert all(torch.equal(start[k], _weights(bundle)[k]) for k in frozen)
    assert not torch.equal(start["actor.0.weight"], _weights(bundle)["actor.0.weight"])
    resumed = finetune_student.run(_cfg(tmp_path, latent_mix=0.5, total_steps=768,
                                        resume=cfg.out / "checkpoints" / "last.zip"))
    assert resumed.config.card["steps"] == 768


def test_latent_mix_weights_are_drawn_per_episode():
    cfg = EnvConfig(episode_steps=3)
    env = vec_env.RotateCupSB3VecEnv(cfg, num_envs=64, seed=3, nthread=1, latent_mix=0.5)
    try:
        first = env.reset()[LATENT_MIX_GROUP][:, 0]
        zero = np.zeros((64, 16), np.float32)
        obs, _, done, infos = env.step(zero)
        assert not done.any()
        np.testing.assert_array_equal(obs[LATENT_MIX_GROUP][:, 0], first)  # held through the episode
        for _ in range(2):
            obs, _, done, infos = env.step(zero)
        assert done.all()
        np.testing.assert_array_equal(infos[0]["terminal_observation"][LATENT_MIX_GROUP][0], first[0])
        second = obs[LATENT_MIX_GROUP][:, 0]
        for w in (first, second):  # about half the episodes mixed, with weights spread over [0, 1]
            assert 16 <= np.count_nonzero(w) <= 48 and ((w >= 0) & (w <= 1)).all() and w.max() > 0.5
        assert not np.array_equal(first, second)
    finally:
        env.close()
    plain = vec_env.RotateCupSB3VecEnv(cfg, num_envs=2, seed=3, nthread=1)
    try:
        assert LATENT_MIX_GROUP not in plain.observation_space.spaces
    finally:
        plain.close()


def test_bad_latent_mix_is_refused(tmp_path):
    with pytest.raises(ValueError, match="latent_mix"):
        _cfg(tmp_path, latent_mix=1.5)
    with pytest.raises(ValueError, match="latent_mix: for a student fine-tune"):
        teacher.Config(out=tmp_path / "x", latent_mix=0.5)
    with pytest.raises(ValueError, match="latent_teacher: .* not a teacher bundle"):
        _cfg(tmp_path, latent_mix=0.5, latent_teacher="student")
