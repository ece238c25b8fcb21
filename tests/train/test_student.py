"""Student distillation on a tiny budget: the latent error drops, the bundle is a student, resume is exact."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from envs.config import EnvConfig
from envs.grasps import generate_grasps
from rotation.policy.bundle import BundleConfig, PolicyBundle, load_bundle
from rotation.train import student


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A random-init teacher bundle and a small grasp cache (one scale bucket) in a temp directory."""
    root = tmp_path_factory.mktemp("student")
    torch.manual_seed(0)
    teacher = PolicyBundle(BundleConfig(card={"kind": "random teacher"}))
    with torch.no_grad():  # a latent that varies strongly with the privileged vector, so there is much to learn
        teacher.net.extractor.encoder.mlp[0].weight.mul_(20.0)
    teacher.save(root / "teacher")
    cache = generate_grasps("cylinder", (0.78,), per_scale=4, batch_size=16, max_rounds=5, seed=0, nthread=1)
    cache.save(root / "grasps.npz")
    return root


def make_cfg(root, out, **kw) -> student.Config:
    env = EnvConfig(object="cylinder", episode_steps=40, grasp_cache=str(root / "grasps.npz"))
    base = dict(teacher=str(root / "teacher"), out=out, num_envs=8, nthread=1, progress=False, env=env)
    return student.Config(**{**base, **kw})


def test_latent_error_goes_down(setup, tmp_path):
    cfg = make_cfg(setup, tmp_path / "run", total_steps=8 * 200, lr=1e-3, log_every=20, checkpoint_every=8 * 100)
    result = student.run(cfg)
    mse = [p["latent_mse"] for p in result.history]
    assert len(mse) == 10 and all(np.isfinite(mse))
    assert mse[0] > 0.05, mse  # the random phi starts far from the teacher's latent
    assert np.mean(mse[-3:]) < 0.25 * mse[0], mse
    assert any("rotation_rate" in p for p in result.history)  # episodes finished and were logged

    bundle = load_bundle(result.bundle_dir)
    assert bundle.config.latent_source == "adaptation"
    assert bundle.config.card["kind"] == "student" and bundle.config.card["final_latent_mse"] == mse[-1]
    assert sorted(p.name for p in (tmp_path / "run").glob("ckpt_*.pt")) == ["ckpt_000000100.pt", "ckpt_000000200.pt"]
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["num_envs"] == 8 and saved["env"]["episode_steps"] == 40
    assert list((tmp_path / "run" / "tb").glob("events.out.tfevents.*"))
    # the teacher's actor is reused untouched
    teacher = load_bundle(setup / "teacher")
    torch.testing.assert_close(bundle.net.actor.state_dict(), teacher.net.actor.state_dict())


def test_resume_is_exact(setup, tmp_path):
    straight = student.run(make_cfg(setup, tmp_path / "a", total_steps=8 * 20, checkpoint_every=8 * 10))
    make_cfg(setup, tmp_path / "b", total_steps=8 * 10, checkpoint_every=8 * 10)
    student.run(make_cfg(setup, tmp_path / "b", total_steps=8 * 10, checkpoint_every=8 * 10))
    resumed = student.run(make_cfg(setup, tmp_path / "b", total_steps=8 * 20, checkpoint_every=8 * 10, resume=True))
    a, b = load_bundle(straight.bundle_dir).net.state_dict(), load_bundle(resumed.bundle_dir).net.state_dict()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_bad_input(setup, tmp_path):
    with pytest.raises(ValueError, match="shipped bundles"):
        student.run(make_cfg(setup, tmp_path / "x", teacher="no_such_teacher"))
    (setup / "teacher_student").mkdir(exist_ok=True)
    load_bundle(setup / "teacher").to_student().save(setup / "teacher_student")
    with pytest.raises(ValueError, match="needs a teacher bundle"):
        student.run(make_cfg(setup, tmp_path / "x", teacher=str(setup / "teacher_student")))
    with pytest.raises(ValueError, match="no checkpoint"):
        student.run(make_cfg(setup, tmp_path / "y", resume=True))
    student.run(make_cfg(setup, tmp_path / "z", total_steps=8 * 2))
    with pytest.raises(ValueError, match="already holds checkpoints"):
        student.run(make_cfg(setup, tmp_path / "z", total_steps=8 * 2))
    with pytest.raises(ValueError, match=r"differs .* in \['lr'\]"):
        student.run(make_cfg(setup, tmp_path / "z", total_steps=8 * 4, lr=1e-2, resume=True))
