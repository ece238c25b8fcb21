"""`rotate finetune-student`: PPO on a distilled student's actor, phi frozen, a privileged critic."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.core import RotateCupVec
from rotation.cli import main
from rotation.policy.bundle import load_bundle, resolve_bundle
from rotation.policy.features import PrivilegedExtractor, StudentExtractor, StudentPPOPolicy
from rotation.train import finetune_student, teacher
from rotation.train.teacher import AdaptiveKLPPO


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
    env = teacher.RotateCupSB3VecEnv(cfg.env_config(), cfg.num_envs, seed=0, obs_groups=teacher.obs_groups(cfg))
    try:
        model = teacher.build_model(cfg, env)
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
        mean = policy.get_distribution({k: torch.as_tensor(obs[k]) for k in teacher.STUDENT_RL_GROUPS}).mode()
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
    model = teacher.load_checkpoint(last)
    assert isinstance(model.policy, StudentPPOPolicy) and model.num_timesteps == 1024
    assert teacher.bundle_from_checkpoint(last).config.card["role"] == "student"


def test_bad_students_are_refused(tmp_path):
    with pytest.raises(ValueError, match="not a student bundle"):
        _cfg(tmp_path, student="teacher")
    with pytest.raises(ValueError, match="student: "):
        _cfg(tmp_path, student=str(tmp_path / "nowhere"))
    with pytest.raises(ValueError, match="neither --init-from"):
        teacher.Config(out=tmp_path / "x", student="student", init_from=resolve_bundle("teacher"))
    with pytest.raises(ValueError, match="net_arch"):
        cfg = _cfg(tmp_path, net_arch=(64, 64))
        env = teacher.RotateCupSB3VecEnv(cfg.env_config(), 2, obs_groups=teacher.obs_groups(cfg))
        try:
            teacher.build_model(cfg, env)
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
