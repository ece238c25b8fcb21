"""scripts/skin_cpu_recipe.py: collections on the vendor-kinematics Xela hand, skin pretraining, export, the probe
and the card check; every command is one its job accepts, a finished step is skipped and a stopped pretraining
resumes; the shipped skin encoder loads strictly and reproduces its card's figures."""

from __future__ import annotations

import json

import pytest
import torch

from rotation import cli
from rotation.configs import dataclass_from_args
from rotation.jobs import collect
from rotation.jobs.recipe import run_steps
from rotation.tactile.models.encoders import ENCODERS, SHIPPED_ENCODERS, fresh_like, load_encoder
from rotation.tactile.models.sparsh_skin import SparshSkin
from rotation.tactile.pretrain import job as pretrain
from rotation.tactile.probes import config as probe

SHIPPED = "sparshskin-tiny-sim"
TOLERANCE = 0.15
"""Relative difference allowed between the card's probe figures and a rerun's. The check's sessions come from a
contact simulation in which last-bit float differences between machines (the C library's maths code paths, for one)
grow into different trajectories within seconds, and the 200-step probe follows its data: on three float variants of
the same commands (the card's machine; another with glibc's FMA code paths, and the same with them turned off by
GLIBC_TUNABLES=glibc.cpu.hwcaps=-FMA) the figures lay up to 6.2% from the card's. The tokens' fingerprint (first
windows, before the trajectories part) agreed to 2e-6 on all three: it is what pins the weights."""


@pytest.fixture(scope="module")
def recipe(load_script):
    return load_script("skin_cpu_recipe")


def _parsed(args):
    module = {"collect": collect, "pretrain": pretrain, "probe": probe}[args[0]]
    parsed = cli.build_parser(args[0]).parse_args(args)
    if hasattr(module, "config_from_args"):
        return module.config_from_args(parsed)
    return dataclass_from_args(module.Config, parsed)


def test_every_step_is_listed_and_parses(recipe, tmp_path):
    out = tmp_path / "r"
    steps = recipe.commands(recipe.Config(out=out, progress=False))
    assert [w.split(":")[0] for w, _ in steps] == ["collect the pretraining sessions", "collect the probe's sessions",
                                                   "pretrain", "export the encoder", "probe", "card check",
                                                   "card check"]
    for folder in ("sessions", "probe_sessions", "card_sessions"):
        (out / folder).mkdir(parents=True)
    for _what, args in steps:
        if args[0] == "python":
            continue
        cfg = _parsed(args)
        if args[0] == "collect":
            assert cfg.skin and cfg.hand == "xela_v4" and cfg.policy == "play"
        elif args[0] == "pretrain":
            assert cfg.encoder == "skin" and cfg.steps == 4000
        else:  # both probes: the same settings for every variant
            assert cfg.encoder == "skin" and str(cfg.checkpoint) == str(out / "encoder")
    main = next(a for w, a in steps if w.startswith("probe"))
    cfg = _parsed(main)
    assert (cfg.steps, cfg.batch_size, cfg.sequence_windows, cfg.lr, cfg.variant_names) == (
        250, 8, 3, 1e-3, ("pretrained", "e2e"))
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
    (out / "card_check").mkdir()
    (out / "card_check" / "results.json").write_text('{"rows": [], "complete": true}')
    assert not any(w.startswith("card") for w, _ in recipe.commands(recipe.Config(out=out)))


def test_dry_run_runs_nothing(recipe, tmp_path, capsys):
    assert recipe.main(["--out", str(tmp_path / "r"), "--dry-run"]) == 0
    assert "rotate collect --skin --hand xela_v4" in capsys.readouterr().out and not (tmp_path / "r").exists()


def test_the_shipped_skin_encoder_reproduces_its_card(recipe, tmp_path):
    """The shipped weights load strictly (load_skin refuses a missing, unexpected or mis-shaped tensor); on the card
    check's sessions their tokens have the card's statistics, which a random start of the same structure does not,
    and the card check's frozen force probe on them gives the card's figures."""
    model = load_encoder(SHIPPED)
    assert isinstance(model, SparshSkin) and model.cfg.size == "tinier"
    card = json.loads((SHIPPED_ENCODERS / SHIPPED / recipe.CARD_FILE).read_text())
    assert card["command"] == recipe.card_lines(SHIPPED)
    steps = recipe.card_commands(SHIPPED, tmp_path)
    assert run_steps("card check", steps[:1], dry_run=False) == 0  # the sessions
    sessions = tmp_path / "card_sessions"
    assert len(card["tokens"]) == model.cfg.embed_dim
    assert recipe.token_summary(SHIPPED, sessions) == pytest.approx(card["tokens"], abs=1e-3)
    torch.manual_seed(0)
    ENCODERS["skin"].save(fresh_like(model), tmp_path / "random" / "encoder.safetensors")
    other = recipe.token_summary(tmp_path / "random", sessions)
    assert max(abs(a - b) for a, b in zip(other, card["tokens"], strict=True)) > 0.1
    assert run_steps("card check", steps[1:], dry_run=False) == 0  # the probe
    got = recipe.card_figures(tmp_path / "card_check")
    assert set(got) == set(card["figures"]) == {"rmse_x_N", "rmse_y_N", "rmse_z_N"}
    for metric, value in card["figures"].items():
        assert got[metric] == pytest.approx(value, rel=TOLERANCE), metric
