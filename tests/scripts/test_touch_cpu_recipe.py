"""scripts/touch_cpu_recipe.py: collections, pretraining, export and the ladder chain; a finished step is skipped, a
stopped pretraining resumes, and every command is one its job accepts."""

from __future__ import annotations

import pytest

from rotation import cli
from rotation.jobs import collect
from rotation.tactile.ladder import job as ladder
from rotation.tactile.pretrain import job as pretrain


@pytest.fixture(scope="module")
def recipe(load_script):
    return load_script("touch_cpu_recipe")


def _parsed(args):
    module = {"collect": collect, "pretrain": pretrain, "touch-report": ladder}[args[0]]
    parsed = cli.build_parser(args[0]).parse_args(args)
    if hasattr(module, "config_from_args"):
        return module.config_from_args(parsed)
    from rotation.configs import dataclass_from_args

    return dataclass_from_args(module.Config, parsed)


def test_the_recipe_lists_every_step_and_each_command_parses(recipe, tmp_path):
    cfg = recipe.Config(policy="teacher", out=tmp_path / "r", progress=False)
    steps = recipe.commands(cfg)
    whats = [w for w, _ in steps]
    assert whats[:6] == [f"collect {name}" for name, *_ in recipe.COLLECTIONS]
    assert whats[6].startswith("pretrain") and whats[7] == "export the encoder"
    second = " (draw 2, seed 201)"
    assert whats[8:] == ["collect the report's sessions", "the information ladder",
                         f"collect the report's sessions{second}", f"the information ladder{second}"]
    reports = [a[a.index("--out") + 1] for _, a in steps if a[0] == "touch-report"]
    assert [r.split("/")[-1] for r in reports] == ["touch_report", "touch_report_201"]  # each draw its own ladder
    for _what, args in steps:
        if args[0] == "python":
            assert args[1].endswith("export_encoder.py")
            continue
        parsed = _parsed(args)  # the job's own parser and validation accept it
        if args[0] == "collect":
            assert parsed.hand == "digit360_v4" and parsed.policy in ("teacher", "random")
    seeds = {int(a[a.index("--seed") + 1]) for _, a in steps if a[0] == "collect"}
    assert {recipe.REPORT_SEED, recipe.REPORT_SEED + 1} <= seeds and len(seeds) == len(recipe.COLLECTIONS) + 2  # new
    parsed = _parsed(next(a for w, a in steps if w.startswith("pretrain")))  # the default: 3 + 1 layers
    assert (parsed.unimodal_layers, parsed.fusion_layers) == (3, 1)
    sized = recipe.commands(recipe.Config(policy="teacher", out=tmp_path / "r", progress=False, layers=()))
    parsed = _parsed(next(a for w, a in sized if w.startswith("pretrain")))  # empty: the size's own
    assert (parsed.unimodal_layers, parsed.fusion_layers) == (None, None)
    with pytest.raises(ValueError, match="layers: give two counts"):
        recipe.Config(policy="teacher", out=tmp_path / "r", layers=(3,))


def test_finished_steps_are_skipped_and_a_stopped_pretraining_resumes(recipe, tmp_path):
    cfg = recipe.Config(policy="teacher", out=tmp_path / "r", steps=300, progress=False)
    run = cfg.out / "pretrain"
    run.mkdir(parents=True)
    (run / "ckpt_000000100.safetensors").write_bytes(b"")
    pre = [a for w, a in recipe.commands(cfg) if w.startswith("pretrain")]
    assert pre and "--resume" in pre[0]
    (run / "ckpt_000000300.safetensors").write_bytes(b"")
    (run / "encoder.safetensors").write_bytes(b"")
    (cfg.out / "encoder").mkdir()
    (cfg.out / "encoder" / "encoder.safetensors").write_bytes(b"")
    (cfg.out / "touch_report").mkdir()
    (cfg.out / "touch_report" / "results.md").write_text("done")
    whats = [w for w, _ in recipe.commands(cfg)]
    assert not any(w.startswith("pretrain") or w.startswith("export") for w in whats)
    assert [w for w in whats if w.startswith("the information")] == ["the information ladder (draw 2, seed 201)"]
    (cfg.out / "touch_report_201").mkdir()
    (cfg.out / "touch_report_201" / "results.md").write_text("done")
    assert not any(w.startswith("the information") for w in [w for w, _ in recipe.commands(cfg)])
    one = recipe.Config(policy="teacher", out=cfg.out, steps=300, progress=False, report_draws=1)
    assert sum(a[0] == "collect" and "report_sessions" in a[a.index("--out") + 1] for _, a in recipe.commands(one)) == 1
    assert recipe.main(["--policy", "teacher", "--out", str(cfg.out), "--steps", "300", "--dry-run"]) == 0


def test_a_policy_is_required(recipe, tmp_path, capsys):
    assert recipe.main(["--out", str(tmp_path / "r")]) == 2
    assert "policy" in capsys.readouterr().err


def test_a_failed_step_is_the_scripts_exit_status(recipe, tmp_path, monkeypatch, capsys):
    """script_main returns the status a recipe's run returns: a step that fails stops the recipe with its status."""
    calls = []
    monkeypatch.setattr(cli, "main", lambda args: calls.append(args) or 3)
    assert recipe.main(["--policy", "teacher", "--out", str(tmp_path / "r"), "--no-progress"]) == 3
    assert len(calls) == 1 and calls[0][0] == "collect"
    assert "ended with status 3" in capsys.readouterr().err
