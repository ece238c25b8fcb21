"""scripts/skin_cpu_recipe.py: collections on the vendor-kinematics Xela hand, skin pretraining, export and the
probe; every command is one its job accepts, a finished step is skipped and a stopped pretraining resumes."""

from __future__ import annotations

import pytest

from rotation import cli
from rotation.configs import dataclass_from_args
from rotation.jobs import collect
from rotation.tactile.pretrain import job as pretrain


@pytest.fixture(scope="module")
def recipe(load_script):
    return load_script("skin_cpu_recipe")


def _parsed(args):
    module = {"collect": collect, "pretrain": pretrain}[args[0]]
    parsed = cli.build_parser(args[0]).parse_args(args)
    if hasattr(module, "config_from_args"):
        return module.config_from_args(parsed)
    return dataclass_from_args(module.Config, parsed)


def test_every_step_is_listed_and_parses(recipe, tmp_path):
    out = tmp_path / "r"
    steps = recipe.commands(recipe.Config(out=out, progress=False))
    assert [w.split(":")[0] for w, _ in steps] == ["collect the pretraining sessions", "collect the probe's sessions",
                                                   "pretrain", "export the encoder", "probe"]
    (out / "sessions").mkdir(parents=True)
    for _what, args in steps:
        if args[0] in ("python", "probe"):  # the probe's checkpoint exists only after the export
            continue
        cfg = _parsed(args)
        if args[0] == "collect":
            assert cfg.skin and cfg.hand == "xela_v4" and cfg.policy == "play"
        else:
            assert cfg.encoder == "skin" and cfg.steps == 8000
    # a pretraining run with its last checkpoint is done; one with an earlier checkpoint resumes
    run = out / "pretrain"
    run.mkdir()
    (run / "ckpt_00000100.safetensors").write_bytes(b"")
    pre = next(a for w, a in recipe.commands(recipe.Config(out=out)) if w.startswith("pretrain"))
    assert "--resume" in pre
    (run / "ckpt_00008000.safetensors").write_bytes(b"")
    assert not any(w.startswith("pretrain") for w, _ in recipe.commands(recipe.Config(out=out)))
    # a stopped probe (its report says complete: false) is run again, and continues; a finished one is skipped
    (out / "probe").mkdir()
    (out / "probe" / "results.md").write_text("| task |\n")
    (out / "probe" / "results.json").write_text('{"rows": [], "complete": false}')
    assert any(w.startswith("probe") for w, _ in recipe.commands(recipe.Config(out=out)))
    (out / "probe" / "results.json").write_text('{"rows": [], "complete": true}')
    assert not any(w.startswith("probe") for w, _ in recipe.commands(recipe.Config(out=out)))


def test_dry_run_runs_nothing(recipe, tmp_path, capsys):
    assert recipe.main(["--out", str(tmp_path / "r"), "--dry-run"]) == 0
    assert "rotate collect --skin --hand xela_v4" in capsys.readouterr().out and not (tmp_path / "r").exists()
