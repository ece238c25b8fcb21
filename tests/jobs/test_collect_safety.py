"""`rotate collect` checks everything before it writes, acts at the bundle's own rate, and never mixes sessions of
different settings (or of a retrained policy) in one collection."""

from __future__ import annotations

import json

import pytest
import torch

from rotation.cli import main
from rotation.data.session_reader import SessionReader
from rotation.jobs import collect, collect_resume
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig


def cfg_for(out, **kw) -> collect.Config:
    return collect.Config(**{**dict(out=out, episodes=1, num_envs=1, episode_steps=3, seed=5, progress=False), **kw})


def teacher_at(path, seed: int = 0, **config) -> str:
    torch.manual_seed(seed)
    return str(PolicyBundle(BundleConfig(card={"note": "untrained"}, **config)).save(path))


def test_refused_run_leaves_nothing_that_refuses_the_corrected_one(tmp_path, capsys):
    out = tmp_path / "touch"
    assert main(["collect", "--policy", str(tmp_path / "no_such_bundle"), "--out", str(out), "--episodes", "1",
                 "--num-envs", "1", "--episode-steps", "3", "--no-progress"]) == 2
    assert "no bundle directory" in capsys.readouterr().err
    assert not (out / collect_resume.MANIFEST).exists()
    collect.run(cfg_for(out))  # the corrected command (a random policy) runs
    assert collect_resume.is_complete(collect.episode_path(out, 0))


def test_a_manifest_of_a_run_that_recorded_nothing_does_not_block(tmp_path):
    out = tmp_path / "touch"
    out.mkdir()
    stale = {"settings": {k: None for k in collect_resume.SETTINGS}, "config": {}}  # e.g. written by an older version
    (out / collect_resume.MANIFEST).write_text(json.dumps(stale))
    collect.run(cfg_for(out))
    assert json.loads((out / collect_resume.MANIFEST).read_text())["settings"]["seed"] == 5


def test_collect_acts_at_the_bundles_rate_and_scale(tmp_path):
    bundle = teacher_at(tmp_path / "slow", control_hz=10.0, action_scale=0.2)
    out = tmp_path / "touch"
    collect.run(cfg_for(out, policy=bundle))
    with SessionReader(collect.episode_path(out, 0)) as r:
        assert r.meta.control_hz == 10.0 and r.stream("joints/position").rate_hz == 10.0
        assert r.stream("digit360/thumb/contact").rate_hz == 100.0  # 10 physics substeps per 10 Hz step
    settings = json.loads((out / collect_resume.MANIFEST).read_text())["settings"]
    assert (settings["control_hz"], settings["action_scale"]) == (10.0, 0.2)


def test_retrained_policy_at_the_same_path_refuses_to_resume(tmp_path):
    bundle = teacher_at(tmp_path / "teacher", seed=0)
    out = tmp_path / "touch"
    collect.run(cfg_for(out, policy=bundle))
    teacher_at(tmp_path / "teacher", seed=1)  # other weights, same directory
    with pytest.raises(ValueError, match="other settings.*policy_weights_sha256"):
        collect.run(cfg_for(out, policy=bundle, episodes=2))
    assert not collect.episode_path(out, 1).exists()


def test_unreadable_manifest_is_named(tmp_path):
    out = tmp_path / "touch"
    out.mkdir()
    (out / collect_resume.MANIFEST).write_text("{not json")
    with pytest.raises(ValueError, match=r"collect.json is not a readable collect manifest"):
        collect.run(cfg_for(out))
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="is a file"):
        collect.run(cfg_for(tmp_path / "file"))
