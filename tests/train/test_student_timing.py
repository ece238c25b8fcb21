"""The student bundle carries the control rate and action scale it was distilled at, so everything that loads it
(evaluate, view, collect, deploy) acts the way it was trained; a timing no bundle may hold is refused up front."""

from __future__ import annotations

import pytest
import torch

from envs.config import EnvConfig
from rotation.bundles import load_bundle
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig
from rotation.train import student


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("student_timing")
    torch.manual_seed(0)
    PolicyBundle(BundleConfig(card={"kind": "random teacher"})).save(root / "teacher")  # a 20 Hz, 1/24 rad teacher
    return root


def cfg_at(root, out, control_hz: float, action_scale: float) -> student.Config:
    env = EnvConfig(object="cup", episode_steps=20, control_hz=control_hz, action_scale=action_scale)  # shipped grasps
    return student.Config(teacher=str(root / "teacher"), out=out, num_envs=4, total_steps=4 * 3, nthread=1,
                          progress=False, env=env)


def test_student_bundle_has_the_rate_and_scale_it_was_trained_at(setup, tmp_path):
    result = student.run(cfg_at(setup, tmp_path / "slow", control_hz=10.0, action_scale=0.2))
    config = load_bundle(result.bundle_dir).config
    assert (config.control_hz, config.action_scale) == (10.0, 0.2)  # not the teacher's 20 Hz / 0.0417 rad


def test_timing_no_bundle_may_hold_is_refused_before_training(setup, tmp_path):
    out = tmp_path / "fast"
    with pytest.raises(ValueError, match=r"env: a student bundle cannot act.*action_scale must be in \(0, 0\.25\]"):
        student.run(cfg_at(setup, out, control_hz=20.0, action_scale=0.5))
    assert not out.exists()  # nothing was written
