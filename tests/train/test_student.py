"""Student distillation on a tiny budget: the latent error drops, the bundle is a student, resume is exact."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from envs.config import EnvConfig
from envs.grasps import generate_grasps
from envs.sim_identity import LEGACY_HAND
from rotation.bundles import load_bundle
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig
from rotation.train import student


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A random-init teacher bundle and a small grasp cache (one scale bucket) in a temp directory; the teacher
    records no sim, so it and its students act on LEGACY_HAND, the hand the cache is generated for."""
    root = tmp_path_factory.mktemp("student")
    torch.manual_seed(0)
    teacher = PolicyBundle(BundleConfig(card={"kind": "random teacher"}))
    with torch.no_grad():  # a latent that varies strongly with the privileged vector, so there is much to learn
        teacher.net.extractor.encoder.mlp[0].weight.mul_(20.0)
    teacher.save(root / "teacher")
    cache = generate_grasps("cylinder", (0.78,), per_scale=4, batch_size=16, max_rounds=20, seed=0, nthread=1,
                            hand=LEGACY_HAND)
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


def test_the_card_gives_the_whole_runs_wall_time(setup, tmp_path):
    """Each checkpoint carries the training time so far; a resumed run's card gives the time over both legs (this
    leg's beside it), and a checkpoint from before that was kept gives this leg's alone, saying so."""
    out = tmp_path / "run"
    student.run(make_cfg(setup, out, total_steps=8 * 10, checkpoint_every=8 * 10))
    ckpt = out / "ckpt_000000010.pt"
    first = torch.load(ckpt, weights_only=False)
    assert 0 < first["wall_time_s"] <= load_bundle(out / "bundle").config.card["wall_time_s"] + 0.05
    torch.save({**first, "wall_time_s": 1000.0}, ckpt)  # as if the first leg had trained for 1000 s
    student.run(make_cfg(setup, out, total_steps=8 * 20, checkpoint_every=8 * 10, resume=True))
    card = load_bundle(out / "bundle").config.card
    assert card["wall_time_this_leg_s"] >= 0  # (ten tiny iterations can round to 0.0 s)
    # the earlier leg's time is the checkpoint's exactly (both figures rounded to 0.1 s)
    assert card["wall_time_s"] - card["wall_time_this_leg_s"] == pytest.approx(1000.0, abs=0.11)
    last = out / "ckpt_000000020.pt"
    assert 1000.0 <= torch.load(last, weights_only=False)["wall_time_s"] <= card["wall_time_s"] + 0.05
    old = torch.load(last, weights_only=False)
    del old["wall_time_s"]
    torch.save(old, last)
    student.run(make_cfg(setup, out, total_steps=8 * 30, checkpoint_every=8 * 10, resume=True))
    card = load_bundle(out / "bundle").config.card
    assert card["wall_time_s"] == card["wall_time_this_leg_s"] < 1000.0
    assert "before checkpoints kept" in card["wall_time_note"]


def test_bad_input(setup, tmp_path):
    with pytest.raises(ValueError, match="shipped bundles"):
        student.run(make_cfg(setup, tmp_path / "x", teacher="no_such_teacher"))
    (setup / "teacher_student").mkdir(exist_ok=True)
    load_bundle(setup / "teacher").to_student().save(setup / "teacher_student")
    with pytest.raises(ValueError, match="not a teacher bundle"):
        student.run(make_cfg(setup, tmp_path / "x", teacher=str(setup / "teacher_student")))
    with pytest.raises(ValueError, match="no checkpoint"):
        student.run(make_cfg(setup, tmp_path / "y", resume=True))
    student.run(make_cfg(setup, tmp_path / "z", total_steps=8 * 2))
    with pytest.raises(ValueError, match=r"already holds a run \(config\.json, run\.json, bundle, curves\.jsonl, tb, "
                                         r"ckpt_000000002\.pt\); pass --resume to continue it, pass --overwrite"):
        student.run(make_cfg(setup, tmp_path / "z", total_steps=8 * 2))
    with pytest.raises(ValueError, match=r"options differ from the run's .*config\.json\): lr: 0\.0003 -> 0\.01"):
        student.run(make_cfg(setup, tmp_path / "z", total_steps=8 * 4, lr=1e-2, resume=True))


# -- runs never lose or mix data -------------------------------------------------------------------------------------


def test_a_folder_holding_any_run_is_refused_and_left_alone(setup, tmp_path):
    out = tmp_path / "teacher_run"  # e.g. a teacher's run folder given as --out by mistake: no ckpt_*.pt in it
    (out / "bundle").mkdir(parents=True)
    (out / "config.json").write_text("{}")
    with pytest.raises(ValueError, match=r"already holds a run \(config\.json, bundle\)"):
        student.run(make_cfg(setup, out, total_steps=8 * 2))
    assert (out / "config.json").read_text() == "{}"


def test_overwrite_clears_the_old_run(setup, tmp_path):
    out = tmp_path / "run"
    student.run(make_cfg(setup, out, total_steps=8 * 4, checkpoint_every=8 * 2))
    assert sorted(p.name for p in out.glob("ckpt_*.pt")) == ["ckpt_000000002.pt", "ckpt_000000004.pt"]
    student.run(make_cfg(setup, out, total_steps=8 * 3, checkpoint_every=8 * 3, overwrite=True))
    assert sorted(p.name for p in out.glob("ckpt_*.pt")) == ["ckpt_000000003.pt"]  # the old ones are gone
    with pytest.raises(ValueError, match="give one of them"):
        make_cfg(setup, out, resume=True, overwrite=True)


def test_failed_resume_keeps_the_config(setup, tmp_path):
    out = tmp_path / "run"
    student.run(make_cfg(setup, out, total_steps=8 * 2))
    saved = (out / "config.json").read_bytes()
    with pytest.raises(ValueError, match=r"options differ .*: env\.episode_steps: 40 -> 30; seed: 0 -> 3"):
        student.run(make_cfg(setup, out, total_steps=8 * 4, seed=3, resume=True,
                             env=EnvConfig(object="cylinder", episode_steps=30,
                                           grasp_cache=str(setup / "grasps.npz"))))
    assert (out / "config.json").read_bytes() == saved


def test_resume_alone_takes_the_runs_options(setup, tmp_path):
    """`--resume` without the run's options (nested env ones included) continues it as it was started."""
    from rotation import cli

    out = tmp_path / "run"
    student.run(make_cfg(setup, out, total_steps=8 * 2, seed=7, lr=2e-3))
    args = cli.build_parser("train-student").parse_args(["train-student", "--out", str(out), "--resume",
                                                         "--total-steps", "32"])
    cfg = student.config_from_args(args)
    assert (cfg.teacher, cfg.num_envs, cfg.seed, cfg.lr, cfg.nthread) == (str(setup / "teacher"), 8, 7, 2e-3, 1)
    assert (cfg.env.object, cfg.env.episode_steps, cfg.env.grasp_cache) == (
        "cylinder", 40, str(setup / "grasps.npz"))
    result = student.run(cfg)
    assert result.history  # it ran on from the checkpoint
    assert sorted(p.name for p in out.glob("ckpt_*.pt"))[-1] == "ckpt_000000004.pt"


def test_damaged_latest_checkpoint_falls_back(setup, tmp_path, capsys):
    out = tmp_path / "run"
    student.run(make_cfg(setup, out, total_steps=8 * 4, checkpoint_every=8 * 2))
    latest = out / "ckpt_000000004.pt"
    latest.write_bytes(latest.read_bytes()[:100])  # truncated
    result = student.run(make_cfg(setup, out, total_steps=8 * 6, checkpoint_every=8 * 2, resume=True))
    err = capsys.readouterr().err
    assert "ckpt_000000004.pt is damaged" in err and "resuming from" in err and "ckpt_000000002.pt" in err
    assert result.history[0]["iteration"] > 2  # it continued from iteration 2
    assert load_bundle(result.bundle_dir).config.card["env_steps"] == 8 * 6
    rows = [json.loads(line)["env_steps"] for line in (out / "curves.jsonl").read_text().splitlines()]
    assert rows == sorted(rows) and len(rows) == len(set(rows))  # points after step 16 were logged once


def test_a_foreign_checkpoint_is_a_clear_error(setup, tmp_path):
    out = tmp_path / "run"
    student.run(make_cfg(setup, out, total_steps=8 * 2))
    torch.save({"weights": torch.zeros(3)}, out / "ckpt_000000009.pt")
    with pytest.raises(ValueError, match=r"ckpt_000000009\.pt is not a train-student checkpoint"):
        student.run(make_cfg(setup, out, total_steps=8 * 12, resume=True))


@pytest.mark.parametrize(("signum", "code"), [(2, 130), (15, 143)])
def test_signal_saves_checkpoint_and_bundle_then_exits_with_its_status(setup, tmp_path, monkeypatch, capsys, signum,
                                                                       code):
    import os

    from rotation import cli

    original = student._log

    def log_then_signal(writer, point):
        original(writer, point)
        if point["iteration"] == 3:
            os.kill(os.getpid(), signum)

    monkeypatch.setattr(student, "_log", log_then_signal)
    out = tmp_path / "run"
    status = cli.main(["train-student", "--teacher", str(setup / "teacher"), "--out", str(out), "--num-envs", "8",
                       "--total-steps", str(8 * 100), "--log-every", "1", "--nthread", "1", "--no-progress",
                       "--env.object", "cylinder", "--env.episode-steps", "40",
                       "--env.grasp-cache", str(setup / "grasps.npz")])
    assert status == code
    captured = capsys.readouterr()
    assert "train-student: interrupted by SIG" in captured.out and "Traceback" not in captured.err
    assert sorted(p.name for p in out.glob("ckpt_*.pt")) == ["ckpt_000000003.pt"]
    card = load_bundle(out / "bundle").config.card
    assert "stopped by SIG" in card["interrupted"] and card["env_steps"] == 8 * 3
    assert [json.loads(line)["iteration"] for line in (out / "curves.jsonl").read_text().splitlines()] == [1, 2, 3]


def test_a_checkpoint_another_run_wrote_is_refused_and_left_alone(setup, tmp_path):
    """The newest ckpt_*.pt in --out is what --resume adopts: it must carry this run's id (run.json). Another run's
    checkpoint (same teacher, another seed) copied in is refused in one line, and nothing changes; a run folder from
    before run ids (no run.json) resumes as before."""
    from envs.errors import RequestRefused

    mine, other = tmp_path / "mine", tmp_path / "other"
    student.run(make_cfg(setup, mine, total_steps=8 * 2, checkpoint_every=8 * 2))
    student.run(make_cfg(setup, other, total_steps=8 * 4, checkpoint_every=8 * 4, seed=3))
    assert (mine / "run.json").is_file()
    (mine / "ckpt_000000004.pt").write_bytes((other / "ckpt_000000004.pt").read_bytes())  # newer than mine
    before = {p: p.read_bytes() for p in mine.rglob("*") if p.is_file()}
    with pytest.raises(RequestRefused, match=r"ckpt_000000004\.pt is not a checkpoint this run wrote"):
        student.run(make_cfg(setup, mine, total_steps=8 * 6, checkpoint_every=8 * 2, resume=True))
    assert {p: p.read_bytes() for p in mine.rglob("*") if p.is_file()} == before
    (other / "run.json").unlink()  # as a folder written before run ids
    assert student.run(make_cfg(setup, other, total_steps=8 * 6, checkpoint_every=8 * 4, seed=3,
                                resume=True)).history
