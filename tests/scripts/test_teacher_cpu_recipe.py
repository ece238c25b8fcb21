"""scripts/teacher_cpu_recipe.py: the five CPU stages chain, skip what is finished and resume what was stopped."""

from __future__ import annotations

import json
import shutil

import pytest

from envs.grasps import default_cache_path
from rotation import cli
from rotation.train import teacher


@pytest.fixture(scope="module")
def recipe(load_script):
    return load_script("teacher_cpu_recipe")


def _fake_bundle(path, card):
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps({"card": card}))


def test_every_stage_is_a_valid_train_teacher_command(recipe, tmp_path):
    out = tmp_path / "recipe"
    todo = recipe.commands(recipe.Config(out=out, progress=False))
    assert [what.split(":")[0] for what, _ in todo] == ["stage 0", "stage1", "stage2", "stage3", "stage4",
                                                        "stage5", "evaluation"]
    # with the files each stage reads in place, the options parse and validate as the job's own Config
    (out / "grasps_unchecked").mkdir(parents=True)
    shutil.copy(default_cache_path("cup"), out / "grasps_unchecked" / "grasps_cup.npz")
    configs = []
    for name, _, _ in recipe.STAGES[:-1]:
        _fake_bundle(out / name / "bundle", {"steps": 1, "interrupted": "stopped"})  # not finished: still to run
    for _, args in recipe.commands(recipe.Config(out=out, progress=False)):
        if args[0] == "train-teacher":
            configs.append(teacher.config_from_args(cli.build_parser("train-teacher").parse_args(args)))
    assert [c.seed for c in configs] == [0, 3, 7, 11, 13]
    assert [c.fall_reward for c in configs] == [-20.0, -20.0, -60.0, -35.0, -60.0]
    assert [c.rotate_back_clip for c in configs] == [0.5, 5.0, 5.0, 5.0, 5.0]
    # stages 1-2 start from the grasps without the hold check, 3-5 from the shipped ones (which evaluation uses)
    assert [bool(c.grasp_cache) for c in configs] == [True, True, False, False, False]
    assert configs[0].init_from is None and [c.init_from for c in configs[1:]] == [
        out / name / "bundle" for name, _, _ in recipe.STAGES[:-1]]
    assert sum(c.total_steps for c in configs) == 37_060_608


def test_finished_stages_are_skipped_and_a_stopped_one_resumes(recipe, tmp_path):
    out = tmp_path / "recipe"
    (out / "grasps_unchecked").mkdir(parents=True)
    (out / "grasps_unchecked" / "grasps_cup.npz").write_bytes(b"")
    steps1, steps2 = recipe.STAGES[0][1], recipe.STAGES[1][1]
    _fake_bundle(out / "stage1" / "bundle", {"steps": steps1})
    _fake_bundle(out / "stage2" / "bundle", {"steps": 123, "interrupted": "stopped by SIGTERM"})
    (out / "stage2" / "checkpoints").mkdir()
    (out / "stage2" / "checkpoints" / "last.zip").write_bytes(b"")
    todo = recipe.commands(recipe.Config(out=out, eval_episodes=0))
    assert [what.split(":")[0] for what, _ in todo] == ["stage2", "stage3", "stage4", "stage5"]
    assert todo[0][1] == ["train-teacher", "--resume", str(out / "stage2" / "checkpoints" / "last.zip"),
                          "--total-steps", str(steps2)]
    assert "--init-from" in todo[1][1] and str(out / "stage2" / "bundle") in todo[1][1]


def test_a_tiny_recipe_runs_end_to_end_and_a_second_call_has_nothing_left(recipe, tmp_path, monkeypatch, capsys):
    """The real jobs, with the stages shrunk to a few updates: each stage starts from the previous one's bundle."""
    tiny = ["--num-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "1", "--episode-steps", "30",
            "--no-overlap"]
    stages = tuple((name, 256, [*(o for o in options if o.startswith("--init-from") or o == "{prev}"), *tiny,
                                "--seed", str(i)]) for i, (name, _, options) in enumerate(recipe.STAGES))
    monkeypatch.setattr(recipe, "STAGES", stages)
    out = tmp_path / "recipe"
    (out / "grasps_unchecked").mkdir(parents=True)
    shutil.copy(default_cache_path("cup"), out / "grasps_unchecked" / "grasps_cup.npz")
    assert recipe.main(["--out", str(out), "--eval-episodes", "8", "--no-progress"]) == 0
    cards = [json.loads((out / name / "bundle" / "config.json").read_text())["card"] for name, _, _ in stages]
    assert [c["steps"] for c in cards] == [256] * 5
    assert [c["train_config"]["init_from"] for c in cards] == [None, *(str(out / n / "bundle") for n, _, _ in
                                                                     stages[:-1])]
    assert "| nominal" in (out / "evaluation" / "results.md").read_text()
    capsys.readouterr()
    assert recipe.main(["--out", str(out), "--no-progress"]) == 0
    assert "every stage is done" in capsys.readouterr().out
