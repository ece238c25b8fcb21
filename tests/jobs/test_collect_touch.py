"""`rotate collect` (sharded, resumable, deterministic sessions) and `rotate inspect-touch` (or inspect-tactile)."""

from __future__ import annotations

import numpy as np
import pytest

from envs import EnvConfig, RotateCupVec
from envs.sensors import kaldi
from rotation.cli import main
from rotation.data.audio import fbank
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.data.session_reader import SessionReader
from rotation.jobs import collect, collect_resume

STEPS = 36  # 1.8 s: long enough for full windows (1.12 s of history) at the end of each episode


def cfg_for(out, **kw):
    """Small random actions (0.15) keep the cup in the hand for all STEPS on these seeds, so every session has full
    windows; at the default 0.5 the random policy may drop it within the first second."""
    return collect.Config(**{**dict(out=out, episodes=2, num_envs=2, episode_steps=STEPS, seed=11, progress=False,
                                    random_scale=0.15), **kw})


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    out = tmp_path_factory.mktemp("touch")
    collect.run(cfg_for(out))
    return out


def test_collect_writes_complete_sessions(collected):
    paths = find_sessions(collected)
    assert [p.relative_to(collected).as_posix() for p in paths] == ["shard_000/episode_000000.h5",
                                                                     "shard_000/episode_000001.h5"]
    with SessionReader(paths[0], require=["digit360/thumb/contact", "labels/force", "labels/object_pose"]) as r:
        assert r.complete and r.meta.source == "sim" and r.meta.extra["episode"] == 0
        assert set(r.meta.properties) == {"scale", "mass", "friction", "com"}
        contact = r.stream("digit360/thumb/contact")
        steps = r.stream("joints/position")
        assert contact.rate_hz == 100.0 and steps.rate_hz == 20.0
        assert len(contact) == 5 * (len(steps) - 1)  # 5 substeps per policy step; steps include t = 0
        force, split = r.stream("labels/force").data[:], r.stream("labels/contact_force").data[:]
        assert split.shape == (len(steps), 4, 2)
        touching = split[..., 0] > 0  # the same force, split at the contact: the magnitude is kept
        assert touching.any() and np.allclose(np.linalg.norm(split, axis=-1)[touching],
                                              np.linalg.norm(force, axis=-1)[touching], rtol=1e-4)
    ds = TouchWindows(paths)
    assert len(ds) > 0 and {"force", "contact_force", "slip", "contact", "object_pose", "priv"} <= set(ds.labels)


def test_collect_resumes_and_is_deterministic(collected, tmp_path):
    first = collect.episode_path(collected, 1)
    with SessionReader(first) as r:
        reference = r.stream("digit360/index/contact").data.copy()
    out = tmp_path / "resume"
    collect.run(cfg_for(out))
    target = collect.episode_path(out, 1)
    stamp = collect.episode_path(out, 0).stat().st_mtime_ns
    target.write_bytes(b"")  # a session whose writer died before writing anything
    collect.run(cfg_for(out, episodes=3))
    assert collect.episode_path(out, 0).stat().st_mtime_ns == stamp  # complete sessions are kept
    with SessionReader(target) as r:  # the broken one is recorded again, identically
        assert r.complete and np.array_equal(r.stream("digit360/index/contact").data, reference)
    assert collect_resume.is_complete(collect.episode_path(out, 2))
    with pytest.raises(ValueError, match=r"other settings \(seed: 11 -> 12\)"):
        collect.run(cfg_for(out, episodes=3, seed=12))


def test_env_observation_equals_the_loader_window(tmp_path):
    """A collected episode replayed in a single env (same seed, same actions): the env's tactile observation and the
    loader's window at the same image frame agree, late enough in the episode that the env's contact ring has
    wrapped around."""
    cfg = collect.Config(out=tmp_path, episodes=1, num_envs=1, episode_steps=56, seed=2, random_scale=0.15,
                         progress=False)
    collect.run(cfg)
    ds = TouchWindows([collect.episode_path(tmp_path, 0)], fingers=["thumb"], audio_features=False)
    last = int(ds.index[-1, 2])
    assert last / 30 > 2.5, "the episode ended too early for this test"
    env = RotateCupVec(EnvConfig(object=cfg.object, tactile=True, episode_steps=cfg.episode_steps), num_envs=1,
                       seed=cfg.seed, nthread=1)
    obs = env.reset(seed=cfg.seed)
    policy = collect._RandomPolicy(1, cfg.seed, cfg.random_scale)
    policy.start(0, 0)
    while int(obs["tactile"].frame[0]) < last - 1:  # 1.5 frames per step: stop on frame last - 1 or last
        obs, *_ = env.step(policy(obs, np.array([True])))
    frame = int(obs["tactile"].frame[0])
    item = ds[int(np.flatnonzero(ds.index[:, 2] == frame)[0])]
    ours = obs["tactile"]["thumb"]
    for m in ("image", "imu", "pressure"):
        assert np.array_equal(ours[m][0], item[m].numpy()), m
    assert np.array_equal(ours["audio"][0], kaldi.fbank(item["audio_wave"].numpy()))  # the same waveform
    assert np.abs(ours["audio"][0] - fbank(item["audio_wave"]).numpy()).max() < 5e-3  # numpy vs torch, float32


def test_cli_collect_and_inspect(tmp_path, collected):
    assert main(["collect", "--episodes", "1", "--num-envs", "1", "--out", str(tmp_path / "c"), "--episode-steps",
                 "2", "--friction-scale", "0.5", "--added-mass", "0.05", "--com-shift", "0", "0", "0.01",
                 "--seed", "3", "--no-progress"]) == 0
    with SessionReader(collect.episode_path(tmp_path / "c", 0)) as r:
        assert r.meta.extra["collect"]["com_shift"] == [0.0, 0.0, 0.01]
    png = tmp_path / "w.png"
    assert main(["inspect-touch", str(collect.episode_path(collected, 0)), "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000
    assert main(["inspect-tactile", str(collect.episode_path(tmp_path / "c", 0)), "--out", str(png)]) == 2  # too short


def test_collect_with_a_teacher_bundle_records_z(tmp_path):
    from rotation.policy.bundle import PolicyBundle
    from rotation.policy.bundle_config import BundleConfig

    path = PolicyBundle(BundleConfig(card={"note": "untrained"})).save(tmp_path / "teacher")
    out = tmp_path / "z"
    collect.run(collect.Config(policy=str(path), out=out, episodes=1, num_envs=1, episode_steps=3, progress=False))
    with SessionReader(collect.episode_path(out, 0), require=["labels/z"]) as r:
        z = r.stream("labels/z")
        assert z.data.shape[1:] == (8,) and len(z) == len(r.stream("joints/position"))
