"""`rotate probe --tasks shake|oas`: the touch benchmarks' multi-class probes (the bottle's content and fill; the
object, action and surface) for every modality variant and end to end, with confusion matrices, on tiny
collections."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from envs.shake_contents import CONTENT_NAMES, FILL_LEVELS
from rotation.jobs import collect
from rotation.tactile.models.encoders import ENCODERS
from rotation.tactile.models.sparshx import SparshX, SparshXConfig
from rotation.tactile.probes import config as probe_config
from rotation.tactile.probes import job as probe


@pytest.fixture(scope="module")
def shake_sessions(tmp_path_factory):
    out = tmp_path_factory.mktemp("shake") / "sessions"
    collect.run(collect.Config(task="shake", episodes=4, out=out, seed=1, shake_s=1.4, progress=False))
    return out


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    model = SparshX(SparshXConfig(size="tinier", modalities=("img", "mic", "imu", "pressure")))
    return ENCODERS["sparshx"].save(model, tmp_path_factory.mktemp("enc") / "encoder.safetensors")


def test_a_tiny_shake_probe_reports_every_modality_with_confusion_matrices(tmp_path, shake_sessions, checkpoint):
    cfg = probe.Config(checkpoint=checkpoint, sessions=(shake_sessions,), out=tmp_path / "probe", tasks=("shake",),
                       budgets=(1.0,), test_fraction=0.25, stride=4, fingers=("index", "thumb"), steps=2,
                       batch_size=4, head_hidden=8, num_workers=0, device="cpu", progress=False, torch_threads=1)
    assert cfg.tasks == ("shake_content", "shake_fill") and cfg.variant_names == probe_config.BENCHMARK_VARIANTS
    report = probe.run(cfg)
    data = json.loads((cfg.out / "results.json").read_text())
    got = {(r["task"], r["variant"], r["budget"], r["metric"]) for r in data["rows"]}
    want = {(t, v, b, m) for t in cfg.tasks for v in ("all", "image", "audio", "imu", "pressure", "e2e")
            for b in (1.0,) for m in ("accuracy", "balanced_accuracy")}
    assert got == want and all(r["task"].startswith("shake") for r in report["rows"])
    assert all(0.0 <= r["value"] <= 1.0 for r in data["rows"])
    for task, classes in (("shake_content", len(CONTENT_NAMES)), ("shake_fill", len(FILL_LEVELS))):
        for variant, matrix in data["confusion"][task].items():
            m = np.asarray(matrix)
            assert m.shape == (classes, classes) and m.sum() == data["test_windows"], (task, variant)
        assert (cfg.out / f"{task}_confusion.png").stat().st_size > 0
    # the baselines: the majority class of the training windows
    assert {b["task"] for b in data["baselines"]} == set(cfg.tasks)


def test_benchmark_variants_and_task_names_are_checked():
    with pytest.raises(ValueError, match="variants"):
        probe.Config(tasks=("shake",), variants=("all", "smell"))
    with pytest.raises(ValueError, match="tasks"):
        probe.Config(tasks=("shake_colour",))


def test_a_tiny_oas_probe_through_the_command_line(tmp_path, checkpoint, capsys):
    """`rotate probe --task oas` (the issue's spelling: argparse takes it for --tasks) on a tiny oas collection."""
    from rotation.cli import main

    sessions = tmp_path / "oas"
    collect.run(collect.Config(task="oas", episodes=3, out=sessions, seed=2, shake_s=1.3, progress=False))
    out = tmp_path / "probe"
    assert main(["probe", "--checkpoint", str(checkpoint), "--sessions", str(sessions), "--task", "oas",
                 "--variants", "all", "e2e", "--budgets", "1.0", "--test-fraction", "0.34", "--fingers", "index",
                 "--stride", "1", "--steps", "1", "--batch-size", "4", "--head-hidden", "8", "--num-workers", "0",
                 "--device", "cpu",
                 "--no-progress", "--out", str(out)]) == 0
    data = json.loads((out / "results.json").read_text())
    assert {r["task"] for r in data["rows"]} == {"oas_object", "oas_action", "oas_surface"}
    assert {r["variant"] for r in data["rows"]} == {"all", "e2e"}
    assert np.asarray(data["confusion"]["oas_surface"]["all"]).shape == (3, 3)
