"""`rotate probe`: the attentive pooler, labels read without rendering, a tiny-budget run writes a well-formed
report, restricted (image-only) encoders, and clear errors on bad input."""

from __future__ import annotations

import json
import math
import shutil

import h5py
import numpy as np
import pytest
import torch

from rotation.cli import main
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.data.window_cache import CachedWindows
from rotation.tactile.models.encoders import ENCODERS
from rotation.tactile.models.pooling import AttentivePooler, ProbeHead
from rotation.tactile.models.sparshx import SparshX, SparshXConfig
from rotation.tactile.probes import config as probe_config
from rotation.tactile.probes import job as probe
from rotation.tactile.probes.data import window_labels


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """An untrained tinier Sparsh-X on image + pressure, saved as `rotate pretrain` exports encoders."""
    torch.manual_seed(0)
    model = SparshX(SparshXConfig(size="tinier", modalities=("img", "pressure")))
    return ENCODERS["sparshx"].save(model, tmp_path_factory.mktemp("enc") / "encoder.safetensors")


def test_attentive_pooler():
    torch.manual_seed(0)
    pool = AttentivePooler(16, heads=4)
    assert 0.0 < float(pool.query.detach().std()) < 0.04  # trunc-normal, std 0.02
    x = torch.randn(3, 10, 16)
    y = pool(x)
    assert y.shape == (3, 16)
    assert torch.allclose(pool(x[:, torch.randperm(10)]), y, atol=1e-5)  # a set function of the tokens
    head = ProbeHead(16, outputs=2, heads=4, hidden=8)
    out = head(x)
    assert out.shape == (3, 2)
    out.sum().backward()
    assert pool.query.grad is None and head.pool.query.grad is not None
    with pytest.raises(ValueError, match="multiple of heads"):
        AttentivePooler(10, heads=4)


def test_labels_read_without_rendering_match_the_windows(touch_sessions, touch_cache, cache_stride):
    paths = [p.resolve() for p in find_sessions(touch_sessions)]
    live = TouchWindows(paths[:2], stride=cache_stride, labels=("force", "slip", "priv"))
    cached = CachedWindows(touch_cache, sessions=paths[:2], labels=("force", "slip", "priv"))
    for name in ("force", "slip", "priv"):
        a, b = window_labels(live, name), window_labels(cached, name)
        assert np.array_equal(a, b) and len(a) == len(live)
        for i in (0, len(live) // 2, len(live) - 1):
            assert np.array_equal(a[i], live[i][name].numpy()), name


def test_tiny_probe_writes_a_well_formed_report(tmp_path, touch_sessions, touch_cache, checkpoint, cache_stride):
    cfg = probe.Config(checkpoint=checkpoint, sessions=(touch_sessions,), cache=touch_cache, out=tmp_path / "probe",
                       budgets=(0.5, 1.0), test_fraction=0.25, stride=cache_stride, steps=2, batch_size=8,
                       head_hidden=16, num_workers=0, device="cpu", progress=False, torch_threads=1)
    report = probe.run(cfg)
    data = json.loads((cfg.out / "results.json").read_text())
    assert data["rows"] == report["rows"]
    metrics = {"force": {"rmse_normal_N", "rmse_shear_N"}, "contact_force": {"rmse_normal_N", "rmse_tangential_N"},
               "slip": {"balanced_accuracy"}, "mass": {"rmse_kg"}, "friction": {"rmse"}}
    want = {(t, v, b, m) for t in metrics for m in metrics[t] for v in probe_config.VARIANTS for b in (0.5, 1.0)}
    got = {(r["task"], r["variant"], r["budget"], r["metric"]) for r in data["rows"]}
    assert got == want and len(data["rows"]) == len(want)
    for r in data["rows"]:
        assert set(r) == {"task", "variant", "budget", "metric", "value"} and math.isfinite(r["value"])
        assert r["value"] >= 0 and (r["metric"] != "balanced_accuracy" or r["value"] <= 1)
    assert data["train_sessions"] == 3 and data["test_sessions"] == 1
    assert data["sessions_per_budget"] == {"0.5": 2, "1.0": 3}  # nested shares of the training sessions
    assert {b["task"] for b in data["baselines"]} == set(metrics)
    md = (cfg.out / "results.md").read_text()
    assert "| task | metric | budget | pretrained | e2e | image_only | baseline |" in md and md.count("\n| ") >= 10
    assert (cfg.out / "probe.png").stat().st_size > 10_000 and (cfg.out / "config.json").is_file()
    assert data["complete"] is True


def test_a_stop_signal_keeps_the_finished_rows(tmp_path, touch_sessions, touch_cache, checkpoint, monkeypatch,
                                                cache_stride):
    """Ctrl-C / SIGTERM during the first (variant, budget): the report holds its rows, marked incomplete."""
    from rotation.interrupt import Interrupted

    class Stopped:  # as if the signal arrived during the first probe run
        requested, signum = True, 15

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def raise_if_requested(self, message=""):
            raise Interrupted(self.signum, message)

    monkeypatch.setattr(probe, "StopSignals", Stopped)
    cfg = probe.Config(checkpoint=checkpoint, sessions=(touch_sessions,), cache=touch_cache, out=tmp_path / "probe",
                       tasks=("force",), budgets=(0.5, 1.0), test_fraction=0.25, stride=cache_stride, steps=2,
                       batch_size=8, head_hidden=16, num_workers=0, device="cpu", progress=False, torch_threads=1)
    with pytest.raises(Interrupted, match="stopped after pretrained at budget 0.5") as err:
        probe.run(cfg)
    assert err.value.exit_code == 143
    data = json.loads((cfg.out / "results.json").read_text())
    assert data["complete"] is False
    assert {(r["variant"], r["budget"]) for r in data["rows"]} == {("pretrained", 0.5)}


def test_image_only_view_shares_the_weights(checkpoint):
    full = ENCODERS["sparshx"].load(checkpoint, None)
    img = ENCODERS["sparshx"].restrict(full, ("img",))
    assert img.token_interface.names == ("img",) and img.cfg.size == "tinier"
    assert torch.equal(img.patch_embed["img"].proj.weight, full.patch_embed["img"].proj.weight)
    assert torch.equal(img.register_tokens[0], full.register_tokens[0])
    with pytest.raises(ValueError, match="no modality"):
        ENCODERS["sparshx"].restrict(full, ("mic",))


def test_bad_input_is_a_clear_error(tmp_path, touch_sessions, touch_cache, capsys, cache_stride):
    with pytest.raises(ValueError, match="budgets"):
        probe.Config(budgets=(0.0, 1.0))
    with pytest.raises(ValueError, match="tasks"):
        probe.Config(tasks=("force", "taste"))
    with pytest.raises(ValueError, match="variants"):
        probe.Config(variants=())
    with pytest.raises(ValueError, match="no encoder checkpoint at .*nothing"):
        probe.run(probe.Config(checkpoint=tmp_path / "nothing.safetensors", sessions=(touch_sessions,),
                               device="cpu", progress=False))
    # image_only needs an encoder with image tokens
    no_img = ENCODERS["sparshx"].save(SparshX(SparshXConfig(size="tinier", modalities=("pressure",))),
                                      tmp_path / "p.safetensors")
    with pytest.raises(ValueError, match="image_only: the encoder .* has no image tokens"):
        probe.run(probe.Config(checkpoint=no_img, sessions=(touch_sessions,), cache=touch_cache, stride=cache_stride,
                               variants=("image_only",), steps=1, num_workers=0, device="cpu", progress=False))
    assert main(["probe", "--budgets", "0.5", "2", "--no-progress"]) == 2
    assert "budgets" in capsys.readouterr().err
    # sessions without labels: a request that cannot be done (status 1), refused before anything is written
    unlabelled = tmp_path / "unlabelled"
    shutil.copytree(touch_sessions, unlabelled)
    for path in unlabelled.rglob("*.h5"):
        with h5py.File(path, "r+") as f:
            del f["streams/labels"]
    out = tmp_path / "probe_unlabelled"
    assert main(["probe", "--checkpoint", "sparshx-tinier-sim", "--sessions", str(unlabelled), "--out", str(out),
                 "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "refused: probe: no sparshx task has its labels" in err and "Traceback" not in err
    assert not out.exists()
