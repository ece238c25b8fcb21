"""`rotate probe` into a folder holding a report of the same options continues it (rotation.tactile.probes.resume):
a stopped run trains only the missing (variant, budget) pairs and ends with the rows of an uninterrupted run, more
variants join a finished table, and a report of other options or another encoder is refused, never overwritten."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from envs.errors import RequestRefused
from rotation.jobs import collect
from rotation.tactile.models.encoders import ENCODERS
from rotation.tactile.models.sparshx import SparshX, SparshXConfig
from rotation.tactile.probes import job as probe
from rotation.tactile.probes.resume import TRACES, _read_traces, write_traces_file
from rotation.tactile.runtime import state_digest


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    out = tmp_path_factory.mktemp("shake") / "sessions"
    collect.run(collect.Config(task="shake", episodes=4, out=out, seed=3, shake_s=1.4, progress=False))
    return out


def _encoder(path, seed):
    torch.manual_seed(seed)
    model = SparshX(SparshXConfig(size="tinier", modalities=("img", "mic", "imu", "pressure")))
    return ENCODERS["sparshx"].save(model, path)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return _encoder(tmp_path_factory.mktemp("enc") / "encoder.safetensors", 0)


def _cfg(sessions, checkpoint, out, **over):
    base = dict(checkpoint=checkpoint, sessions=(sessions,), out=out, tasks=("shake_content",), budgets=(0.5, 1.0),
                variants=("all",), test_fraction=0.25, stride=4, fingers=("index", "thumb"), steps=4, batch_size=4,
                head_hidden=8, num_workers=0, device="cpu", progress=False, torch_threads=1, lr=1e-2)
    return probe.Config(**(base | over))


def _values(report):
    return {(r["variant"], r["budget"], r["metric"]): r["value"] for r in report["rows"]}


def test_a_stopped_report_continues_to_the_rows_of_an_uninterrupted_run(tmp_path, sessions, checkpoint, capsys):
    whole = probe.run(_cfg(sessions, checkpoint, tmp_path / "whole"))
    out = tmp_path / "stopped"
    probe.run(_cfg(sessions, checkpoint, out))
    saved = json.loads((out / "results.json").read_text())  # as a stop after the first budget leaves it
    saved["rows"] = [r for r in saved["rows"] if r["budget"] == 0.5]
    saved["complete"] = False
    (out / "results.json").write_text(json.dumps(saved))
    capsys.readouterr()
    continued = probe.run(_cfg(sessions, checkpoint, out))
    assert "holds 1 finished (variant, budget) pair(s) of these options: kept; 1 to train" in capsys.readouterr().out
    assert continued["complete"] and _values(continued) == pytest.approx(_values(whole), abs=1e-6)
    assert len(continued["rows"]) == len(whole["rows"]) == 4
    assert continued["sessions_per_budget"] == whole["sessions_per_budget"]


def test_more_variants_join_a_finished_table_and_its_rows_are_not_trained_again(tmp_path, sessions, checkpoint,
                                                                             capsys):
    out = tmp_path / "probe"
    first = probe.run(_cfg(sessions, checkpoint, out))
    capsys.readouterr()
    both = probe.run(_cfg(sessions, checkpoint, out, variants=("image",), num_workers=0, token_cache_gb=0.0))
    assert "holds 2 finished (variant, budget) pair(s) of these options: kept; 2 to train" in capsys.readouterr().out
    assert {r["variant"] for r in both["rows"]} == {"all", "image"} and len(both["rows"]) == 8
    assert {k: v for k, v in _values(both).items() if k[0] == "all"} == _values(first)
    assert set(both["confusion"]["shake_content"]) == {"all", "image"}
    table = (out / "results.md").read_text()
    assert "| task | metric | budget | all | image | baseline |" in table
    again = probe.run(_cfg(sessions, checkpoint, out))  # everything there: nothing trained, nothing lost
    assert _values(again) == _values(both)


def test_a_report_of_other_options_or_another_encoder_is_refused_and_kept(tmp_path, sessions, checkpoint):
    out = tmp_path / "probe"
    probe.run(_cfg(sessions, checkpoint, out))
    before = (out / "results.json").read_bytes()
    with pytest.raises(RequestRefused, match=r"other options \(steps: 4 -> 5\)"):
        probe.run(_cfg(sessions, checkpoint, out, steps=5))
    with pytest.raises(RequestRefused, match="encoder weights"):
        probe.run(_cfg(sessions, _encoder(tmp_path / "other.safetensors", 1), out))
    assert (out / "results.json").read_bytes() == before
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "results.json").write_text('{"episodes": []}')
    with pytest.raises(RequestRefused, match="not a probe report"):
        probe.run(_cfg(sessions, checkpoint, tmp_path / "elsewhere"))
    (tmp_path / "elsewhere" / "results.json").write_text('{"rows": [')
    with pytest.raises(RequestRefused, match="cannot be read"):
        probe.run(_cfg(sessions, checkpoint, tmp_path / "elsewhere"))


def test_traces_and_the_state_digest(tmp_path, checkpoint):
    traces = {"pose": {"pretrained": {"pred": np.arange(6.0).reshape(3, 2), "true": np.ones((3, 2)),
                                      "time": np.array([0.1, 0.2, 0.3]), "session": np.array([0, 0, 1])}}}
    write_traces_file(traces, tmp_path)
    back = _read_traces(tmp_path / TRACES)
    assert back.keys() == traces.keys() and back["pose"].keys() == {"pretrained"}
    for name, value in traces["pose"]["pretrained"].items():
        np.testing.assert_array_equal(back["pose"]["pretrained"][name], value)
    a = probe.load_encoder(checkpoint)
    assert state_digest(a) == state_digest(probe.load_encoder(checkpoint))
    with torch.no_grad():
        next(a.parameters()).view(-1)[0] += 1e-3
    assert state_digest(a) != state_digest(probe.load_encoder(checkpoint))
