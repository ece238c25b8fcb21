"""GPU-recipe training on Warp's CPU device: a tiny teacher run writes a bundle that loads and evaluates like a
CPU-trained one, the student distills on the warp backend, and the command line starts from the GPU recipe."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rotation import cli
from rotation.policy.bundle import load_bundle
from rotation.train import teacher
from rotation.train.teacher_warp import GPU_RECIPE


def test_the_command_line_starts_from_the_gpu_recipe():
    parser = cli.build_parser(only="train-teacher")
    args = parser.parse_args(["train-teacher", "--backend", "warp", "--device", "cpu", "--n-epochs", "2"])
    cfg = teacher.config_from_args(args)
    assert (cfg.num_envs, cfg.n_steps, cfg.learning_rate) == (GPU_RECIPE["num_envs"], GPU_RECIPE["n_steps"],
                                                              GPU_RECIPE["learning_rate"])
    assert cfg.n_epochs == 2 and cfg.device == "cpu"  # given options win
    assert cfg.batch_size == cfg.num_envs * cfg.n_steps // 4
    cpu = teacher.config_from_args(parser.parse_args(["train-teacher"]))
    assert cpu == teacher.Config()  # the cpu backend keeps its own defaults


def test_tiny_teacher_run_writes_a_bundle_that_evaluates(tmp_path, capsys):
    cfg = teacher.Config(backend="warp", device="cpu", num_envs=4, n_steps=4, batch_size=8, n_epochs=2,
                         total_steps=32, checkpoint_every=16, out=tmp_path / "teacher", progress=False)
    bundle = teacher.run(cfg)
    loaded = load_bundle(tmp_path / "teacher" / "bundle")
    assert loaded.config.latent_source == "privileged" and loaded.config.card["backend"] == "warp"
    obs = {"proprio": np.zeros((3, 32), np.float32), "priv": np.zeros(9, np.float32)}
    assert np.allclose(loaded.act(obs), bundle.act(obs))
    rows = [json.loads(line) for line in (tmp_path / "teacher" / "curves.jsonl").read_text().splitlines()]
    assert rows and rows[-1]["steps"] == 32
    assert any((tmp_path / "teacher" / "tb").rglob("events.out.tfevents.*"))
    status = cli.main(["evaluate", "--backend", "warp", "--warp-device", "cpu", "--policy",
                       f"t={tmp_path / 'teacher' / 'bundle'}", "--episodes", "2", "--num-envs", "2",
                       "--episode-steps", "4", "--out", str(tmp_path / "eval"), "--no-progress"])
    assert status == 0, capsys.readouterr().err
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert results["rows"][0]["policy"] == "t"
    status = cli.main(["evaluate", "--policy", f"t={tmp_path / 'teacher' / 'bundle'}", "--episodes", "2",
                       "--num-envs", "2", "--episode-steps", "4", "--out", str(tmp_path / "eval_cpu"),
                       "--no-progress"])  # and on the cpu backend, like a teacher trained there
    assert status == 0, capsys.readouterr().err

    from rotation.train import student

    scfg = student.Config(teacher=str(tmp_path / "teacher" / "bundle"), out=tmp_path / "student", backend="warp",
                          num_envs=2, total_steps=8, checkpoint_every=8, log_every=2, progress=False)
    result = student.run(scfg)
    assert load_bundle(result.bundle_dir).config.latent_source == "adaptation"


def test_warp_teacher_refuses_resume(tmp_path):
    with pytest.raises(ValueError, match="backend 'warp' cannot --resume"):
        teacher.Config(backend="warp", device="cpu", resume=tmp_path / "last.zip")


@pytest.mark.gpu
def test_tiny_teacher_run_on_the_gpu(tmp_path):
    cfg = teacher.Config(backend="warp", device="cuda", num_envs=256, n_steps=8, batch_size=512, n_epochs=2,
                         total_steps=256 * 8 * 2, out=tmp_path / "teacher", progress=False)
    teacher.run(cfg)
    assert load_bundle(tmp_path / "teacher" / "bundle").config.card["backend"] == "warp"
