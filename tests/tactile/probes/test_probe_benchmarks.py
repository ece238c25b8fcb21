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



def test_frozen_tokens_computed_once_train_the_heads_the_encoder_in_every_step_trains(tmp_path, shake_sessions,
                                                                                      checkpoint, capsys):
    """The token cache changes the cost, not the result: heads trained on tokens computed once end with the
    parameters of heads trained with the encoder run in every step (same batches, same tokens), and a report made
    with the cache equals one without it; a limit too small falls back to the encoder in the step."""
    from tqdm import tqdm

    from rotation.tactile.probes.tokens import frozen_tokens
    from rotation.tactile.probes.train import Probes, train_probes

    base = dict(checkpoint=checkpoint, sessions=(shake_sessions,), tasks=("shake_content",), budgets=(0.5, 1.0),
                variants=("all", "image"), test_fraction=0.25, stride=4, fingers=("index", "thumb"), steps=6,
                batch_size=4, head_hidden=8, num_workers=0, device="cpu", progress=False, torch_threads=1,
                lr=1e-2)
    cfg = probe.Config(out=tmp_path / "cached", **base)
    tasks, groups = probe._prepare(cfg)
    data, encoder, device = groups[False], probe.load_encoder(checkpoint), torch.device("cpu")
    stats = {"shake_content": (torch.zeros(1), torch.ones(1))}
    heads = []
    for train_set in (data.train, frozen_tokens(encoder, data.train, ("content",), 4, 0, device, False)):
        torch.manual_seed(0)
        probes = Probes(encoder, True, tasks, cfg)
        train_probes(probes, train_set, tasks, cfg, stats, 1.0, device, False, tqdm(disable=True), None, "t")
        heads.append(probes.heads.state_dict())
    assert any(not torch.equal(v, Probes(encoder, True, tasks, cfg).heads.state_dict()[k])
               for k, v in heads[0].items())  # the heads did train
    for k, v in heads[0].items():
        torch.testing.assert_close(heads[1][k], v, rtol=1e-5, atol=1e-6)

    cached = probe.run(cfg)
    in_step = probe.run(probe.Config(out=tmp_path / "in_step", token_cache_gb=0.0, **base))
    tiny = probe.run(probe.Config(out=tmp_path / "tiny", token_cache_gb=1e-9, **base))
    assert capsys.readouterr().out.count("the encoder runs in every step instead") == 2  # the tiny run's variants

    def values(report):
        return {(r["variant"], r["budget"], r["metric"]): r["value"] for r in report["rows"]}

    assert values(cached).keys() == values(in_step).keys() and len(values(cached)) == 8
    assert values(cached) == pytest.approx(values(in_step), abs=1e-6) and values(tiny) == values(in_step)
    assert cached["confusion"] == in_step["confusion"]


def test_token_cache_limit_is_checked():
    with pytest.raises(ValueError, match="token_cache_gb"):
        probe.Config(token_cache_gb=-1.0)
