"""Teacher runs never lose or mix data: resume continues the step count and keeps the run's options, folder, start
and wall time; an existing run is refused without --resume or cleared with --overwrite; curves are on disk with each
checkpoint; a damaged, foreign or other program's checkpoint is a clear error or a fallback, never a silent restart.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from tiny_teacher import tiny_config

from rotation.bundles import load_bundle
from rotation.train import ppo, teacher, teacher_config, vec_env
from rotation.train.ppo import AdaptiveKLPPO, KLSchedule


def test_resume_continues_the_step_count(tmp_path):
    first = tiny_config(tmp_path, total_steps=2048)
    teacher.run(first)
    ckpt = first.out / "checkpoints" / "last.zip"
    assert AdaptiveKLPPO.load(ckpt, device="cpu").num_timesteps == 2048
    lr_before = AdaptiveKLPPO.load(ckpt, device="cpu").lr_schedule.lr
    teacher.run(tiny_config(tmp_path, total_steps=4096, resume=ckpt))
    resumed = AdaptiveKLPPO.load(ckpt, device="cpu")
    assert resumed.num_timesteps == 4096
    assert isinstance(resumed.lr_schedule, KLSchedule) and resumed.lr_schedule.lr > 0
    assert lr_before > 0
    assert (first.out / "checkpoints" / "step_0000004096.zip").is_file()
    assert load_bundle(first.out / "bundle").config.card["steps"] == 4096


def _curve_steps(out) -> list[int]:
    return [json.loads(line)["steps"] for line in (out / "curves.jsonl").read_text().splitlines()]


def test_existing_run_is_refused_without_resume(tmp_path):
    cfg = tiny_config(tmp_path, total_steps=1024)
    teacher.run(cfg)
    before = {p: p.read_bytes() for p in (cfg.out / "config.json", cfg.out / "curves.jsonl",
                                          cfg.out / "checkpoints" / "last.zip")}
    with pytest.raises(ValueError, match=r"already holds a run \(config\.json, run\.json, checkpoints, bundle, "
                                         r"curves\.jsonl.*--resume .*last\.zip to continue it, pass --overwrite"):
        teacher.run(tiny_config(tmp_path, total_steps=1024, seed=5))
    assert {p: p.read_bytes() for p in before} == before  # nothing was touched


def test_overwrite_clears_the_old_run_first(tmp_path):
    out = tmp_path / "run"
    (out / "bundle").mkdir(parents=True)
    (out / "bundle" / "stale.txt").write_text("from an older run")
    (out / "curves.jsonl").write_text(json.dumps({"steps": 99_999, "r": 1.0}) + "\n")
    (out / "notes.txt").write_text("the user's own file")
    teacher.run(tiny_config(tmp_path, total_steps=1024, overwrite=True))
    assert not (out / "bundle" / "stale.txt").exists()
    assert 99_999 not in _curve_steps(out)
    assert (out / "notes.txt").read_text() == "the user's own file"  # only the run's outputs are deleted


def test_resume_alone_takes_the_runs_options_and_folder(tmp_path):
    """`rotate train-teacher --resume CKPT --total-steps N` continues the run as it was started: the options it
    leaves out (here non-default ones) are the run's, --out is the checkpoint's run folder; a given option that
    may not change is still refused."""
    from rotation import cli

    out = tmp_path / "run"
    start = ["train-teacher", "--out", str(out), "--num-envs", "16", "--n-steps", "32", "--batch-size", "128",
             "--n-epochs", "1", "--gamma", "0.95", "--total-steps", "512", "--checkpoint-every", "512",
             "--episode-steps", "50", "--seed", "4", "--no-progress"]
    assert cli.main(start) == 0
    ckpt = out / "checkpoints" / "last.zip"
    saved = json.loads((out / "config.json").read_text())
    args = cli.build_parser("train-teacher").parse_args(["train-teacher", "--resume", str(ckpt),
                                                         "--total-steps", "1024"])
    cfg = teacher.config_from_args(args)
    assert cfg.out == out and cfg.total_steps == 1024 and cfg.resume == ckpt
    assert (cfg.num_envs, cfg.n_steps, cfg.batch_size, cfg.gamma, cfg.seed, cfg.episode_steps) == (
        16, 32, 128, 0.95, 4, 50)
    assert cli.main(["train-teacher", "--resume", str(ckpt), "--total-steps", "1024", "--no-progress"]) == 0
    assert AdaptiveKLPPO.load(ckpt, device="cpu").num_timesteps == 1024
    assert {k: v for k, v in json.loads((out / "config.json").read_text()).items()
            if k not in ("total_steps", "resume", "progress")} == {
        k: v for k, v in saved.items() if k not in ("total_steps", "resume", "progress")}
    args = cli.build_parser("train-teacher").parse_args(["train-teacher", "--resume", str(ckpt), "--gamma", "0.9",
                                                         "--total-steps", "2048"])
    with pytest.raises(ValueError, match=r"gamma: 0\.95 -> 0\.9"):
        teacher.run(teacher.config_from_args(args))


def test_resume_with_other_ppo_options_is_refused_and_keeps_config(tmp_path):
    first = tiny_config(tmp_path, total_steps=1024)
    teacher.run(first)
    ckpt = first.out / "checkpoints" / "last.zip"
    saved = (first.out / "config.json").read_bytes()
    with pytest.raises(ValueError, match=r"options differ from the run's .*config\.json\): gamma: 0\.99 -> 0\.9; "
                                         r"n_epochs: 4 -> 2\. .* only checkpoint_every, critic_warmup, device, "
                                         r"init_from, out, overlap, overwrite"):
        teacher.run(tiny_config(tmp_path, total_steps=2048, resume=ckpt, n_epochs=2, gamma=0.9))
    assert (first.out / "config.json").read_bytes() == saved  # a failed resume writes nothing
    # without the run's config.json the checkpoint's own record still catches PPO options
    (first.out / "config.json").unlink()
    with pytest.raises(ValueError, match=r"recorded in .*last\.zip\): clip_range: 0\.2 -> 0\.3"):
        teacher.run(tiny_config(tmp_path, total_steps=2048, resume=ckpt, clip_range=0.3))


def test_resume_refuses_a_regenerated_grasp_cache_at_the_same_path(tmp_path):
    """The options name the grasp cache by its path; config.json and the bundle's card also record its digest, so a
    resume from a file regenerated in place (every episode would start elsewhere) is refused, not silently mixed."""
    import shutil

    from envs.grasp_cache import default_cache_path

    cache = tmp_path / "grasps_cup.npz"
    shutil.copy(default_cache_path("cup"), cache)
    first = tiny_config(tmp_path, total_steps=1024, grasp_cache=str(cache))
    teacher.run(first)
    saved = json.loads((first.out / "config.json").read_text())
    digest = saved[teacher.GRASPS_KEY]
    assert len(digest) == 16 and load_bundle(first.out / "bundle").config.card[teacher.GRASPS_KEY] == digest
    ckpt = first.out / "checkpoints" / "last.zip"
    with np.load(cache) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["grasps"] = arrays["grasps"][:, ::-1].copy()  # the same path, the grasps in another order
    np.savez(cache, **arrays)
    with pytest.raises(ValueError, match=r"grasp cache \(.*grasps_cup\.npz\) is not the file the run started from"):
        teacher.run(tiny_config(tmp_path, total_steps=2048, grasp_cache=str(cache), resume=ckpt))
    assert json.loads((first.out / "config.json").read_text()) == saved  # a refused resume writes nothing
    # a run recorded before the digest was kept resumes as before (its cache cannot be compared)
    (first.out / "config.json").write_text(json.dumps({k: v for k, v in saved.items() if k != teacher.GRASPS_KEY}))
    teacher.run(tiny_config(tmp_path, total_steps=2048, grasp_cache=str(cache), resume=ckpt))
    assert json.loads((first.out / "config.json").read_text())[teacher.GRASPS_KEY] != digest


def test_curves_are_on_disk_with_each_checkpoint(tmp_path, monkeypatch):
    """A crash (here an exception after the second checkpoint, as a SIGKILL would) keeps the curve rows so far."""
    original = ppo.Checkpoints.save

    def save_then_crash(self):
        path = original(self)
        if self.num_timesteps >= 2048:
            raise RuntimeError("killed")
        return path

    monkeypatch.setattr(ppo.Checkpoints, "save", save_then_crash)
    cfg = tiny_config(tmp_path, total_steps=4096, checkpoint_every=1024)
    with pytest.raises(RuntimeError, match="killed"):
        teacher.run(cfg)
    steps = _curve_steps(cfg.out)
    assert steps and max(steps) <= 2048 and steps == sorted(steps)


def test_damaged_last_checkpoint_falls_back_to_the_previous_intact_one(tmp_path, capsys):
    cfg = tiny_config(tmp_path, total_steps=2048, checkpoint_every=1024)
    teacher.run(cfg)
    folder = cfg.out / "checkpoints"
    assert sorted(p.name for p in folder.glob("step_*.zip")) == ["step_0000001024.zip", "step_0000002048.zip"]
    for name in ("last.zip", "step_0000002048.zip"):  # truncated, as by a full disk
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: len(data) // 2])
    teacher.run(tiny_config(tmp_path, total_steps=3072, checkpoint_every=1024, resume=folder / "last.zip"))
    err = capsys.readouterr().err
    assert "warning: checkpoint" in err and "last.zip is damaged" in err and "step_0000001024.zip" in err
    assert AdaptiveKLPPO.load(folder / "last.zip", device="cpu").num_timesteps == 3072
    steps = _curve_steps(cfg.out)
    assert steps == sorted(steps)  # the rows after step 1024 of the lost part were dropped before appending


def test_checkpoints_of_other_programs_are_clear_errors(tmp_path):
    import zipfile

    import gymnasium as gym
    from stable_baselines3 import PPO

    (tmp_path / "other.zip").write_bytes(b"")
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as z:
        z.writestr("hello.txt", "not a model")
    with pytest.raises(ValueError, match=r"other\.zip is not a train-teacher checkpoint: a zip of \['hello\.txt'\]"):
        teacher.run(tiny_config(tmp_path, resume=tmp_path / "other.zip"))
    PPO("MlpPolicy", gym.make("Pendulum-v1"), n_steps=64, batch_size=64).save(tmp_path / "pendulum.zip")
    with pytest.raises(ValueError, match=r"pendulum\.zip cannot be loaded as a train-teacher checkpoint "
                                         r"\(ValueError: Observation spaces do not match"):
        teacher.run(tiny_config(tmp_path, resume=tmp_path / "pendulum.zip"))
    # the teacher's observation space, but SB3's plain policy instead of the privileged one
    env = vec_env.RotateCupSB3VecEnv(tiny_config(tmp_path).env_config(), 2, seed=0,
                                     obs_groups=teacher_config.TEACHER_GROUPS)
    PPO("MultiInputPolicy", env, n_steps=64, batch_size=64).save(tmp_path / "plain.zip")
    env.close()
    with pytest.raises(ValueError, match=r"plain\.zip holds a MultiInputActorCriticPolicy with a "
                                         r"CombinedExtractor features extractor, not the teacher's privileged policy"):
        teacher.run(tiny_config(tmp_path, resume=tmp_path / "plain.zip"))
    (tmp_path / "garbage.zip").write_bytes(b"PK\x03\x04 not really")
    with pytest.raises(ValueError, match=r"garbage\.zip is damaged .*not a readable zip file"):
        teacher.run(tiny_config(tmp_path, resume=tmp_path / "garbage.zip"))
    assert not (tmp_path / "run" / "config.json").exists()  # none of these wrote anything


def test_a_checkpoint_another_run_wrote_is_refused_and_left_alone(tmp_path):
    """Each run records an id (run.json) and every checkpoint it writes proves it belongs (last.zip.owner.json: the
    id and the file's sha256). Another run's last.zip copied over this run's is refused in one line, and nothing
    in either folder changes; a run folder from before run ids (no run.json) resumes as it always did."""
    from envs.errors import RequestRefused

    mine = tiny_config(tmp_path / "mine", total_steps=1024)
    other = tiny_config(tmp_path / "other", total_steps=1024, seed=5)
    teacher.run(mine)
    teacher.run(other)
    assert (mine.out / "run.json").is_file() and (mine.out / "checkpoints" / "last.zip.owner.json").is_file()
    last = mine.out / "checkpoints" / "last.zip"
    last.write_bytes((other.out / "checkpoints" / "last.zip").read_bytes())
    for f in mine.out.joinpath("checkpoints").glob("step_*"):
        f.unlink()  # no earlier checkpoint to fall back to
    before = {p: p.read_bytes() for p in mine.out.rglob("*") if p.is_file()}
    with pytest.raises(RequestRefused, match="last.zip is not a checkpoint this run wrote"):
        teacher.run(tiny_config(tmp_path / "mine", total_steps=2048, resume=last))
    assert {p: p.read_bytes() for p in mine.out.rglob("*") if p.is_file()} == before
    (other.out / "run.json").unlink()  # as a folder written before run ids
    teacher.run(tiny_config(tmp_path / "other", total_steps=2048, seed=5,
                            resume=other.out / "checkpoints" / "last.zip"))
    assert AdaptiveKLPPO.load(other.out / "checkpoints" / "last.zip", device="cpu").num_timesteps == 2048


def test_a_resume_into_another_folder_logs_there(tmp_path):
    """A checkpoint remembers the TensorBoard folder of the run that saved it; continuing it into another --out
    writes its TensorBoard events there, and adds nothing to the first run's folder."""
    first = tiny_config(tmp_path / "a", total_steps=1024)
    teacher.run(first)
    events = sorted(p.name for p in (first.out / "tb").rglob("events.*"))
    teacher.run(tiny_config(tmp_path / "b", total_steps=2048, resume=first.out / "checkpoints" / "last.zip"))
    assert sorted(p.name for p in (first.out / "tb").rglob("events.*")) == events
    assert list((tmp_path / "b" / "run" / "tb").rglob("events.*"))


def test_a_resumed_run_keeps_where_it_started_and_its_whole_wall_time(tmp_path):
    """A resume has no --init-from, yet its config.json and bundle card still name the bundle the run started from;
    the card's wall time is the run's over both legs (each checkpoint carries the time so far), this leg's beside it;
    a checkpoint from before wall times were kept gives this leg's alone, and says so."""
    from rotation.policy.bundle import resolve_bundle
    from rotation.runs import run_id, write_owner

    start = resolve_bundle("teacher")
    cfg = tiny_config(tmp_path, total_steps=1024, init_from=start, critic_warmup=1)
    teacher.run(cfg)
    ckpt = cfg.out / "checkpoints" / "last.zip"
    first_leg = AdaptiveKLPPO.load(ckpt, device="cpu").train_wall_s
    first_card = load_bundle(cfg.out / "bundle").config.card
    assert 0 < first_leg and first_card["wall_time_s"] == pytest.approx(first_leg, abs=0.06)  # the same figure
    model = AdaptiveKLPPO.load(ckpt, device="cpu")
    model.train_wall_s = 1000.0  # as if the first leg had trained for 1000 s
    model.save(ckpt)
    write_owner(ckpt, run_id(cfg.out, create=False))
    teacher.run(tiny_config(tmp_path, total_steps=2048, init_from=None, critic_warmup=1, resume=ckpt))
    card = load_bundle(cfg.out / "bundle").config.card
    assert card["started_from"] == str(start)
    assert json.loads((cfg.out / "config.json").read_text())["started_from"] == str(start)
    assert card["wall_time_this_leg_s"] > 0
    # the earlier leg's time is the checkpoint's (rounded to 0.1 s; this leg's is timed from just before learning)
    assert 1000.0 - 0.06 <= card["wall_time_s"] - card["wall_time_this_leg_s"] <= 1000.5
    assert card["wall_time_s"] == pytest.approx(AdaptiveKLPPO.load(ckpt, device="cpu").train_wall_s, abs=0.06)
    # a third leg still names it (carried from the resumed run's own record)
    teacher.run(tiny_config(tmp_path, total_steps=3072, init_from=None, critic_warmup=1, resume=ckpt))
    assert load_bundle(cfg.out / "bundle").config.card["started_from"] == str(start)
    # a checkpoint saved before checkpoints kept the time: this leg's alone, with a note
    old = AdaptiveKLPPO.load(ckpt, device="cpu")
    del old.train_wall_s
    old.save(ckpt)
    write_owner(ckpt, run_id(cfg.out, create=False))
    teacher.run(tiny_config(tmp_path, total_steps=4096, init_from=None, critic_warmup=1, resume=ckpt))
    card = load_bundle(cfg.out / "bundle").config.card
    assert card["wall_time_s"] == card["wall_time_this_leg_s"] < 1000.0
    assert "before checkpoints kept" in card["wall_time_note"]

