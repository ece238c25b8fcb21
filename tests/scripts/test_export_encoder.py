"""scripts/export_encoder.py halves a Sparsh-X file with a measured error; the shipped encoder loads by name."""

from __future__ import annotations

import pytest
import torch

from rotation.tactile.models.encoders import ENCODERS, load_encoder, shipped_encoders
from rotation.tactile.models.sparshx import SparshX, SparshXConfig


def test_export_halves_the_weights_and_keeps_the_tokens(load_script, tmp_path):
    torch.manual_seed(0)
    model = SparshX(SparshXConfig(size="tinier", modalities=("imu", "pressure")))
    src = ENCODERS["sparshx"].save(model, tmp_path / "run" / "encoder.safetensors")
    mod = load_script("export_encoder")
    out = mod.run(mod.Config(checkpoint=src.parent, out=tmp_path / "ship"))
    assert out["bytes"] < 0.6 * src.stat().st_size
    assert 0 < out["relative_error"] < 1e-2
    loaded = load_encoder(tmp_path / "ship")
    assert all(p.dtype == torch.float32 for p in loaded.parameters())  # cast back on load
    with pytest.raises(ValueError, match="dtype: one of"):
        mod.run(mod.Config(checkpoint=src.parent, out=tmp_path / "bad", dtype="int8"))


def test_the_shipped_encoder_loads_by_name():
    assert "sparshx-tinier-sim" in shipped_encoders()
    model = load_encoder("sparshx-tinier-sim")
    assert model.cfg.size == "tinier" and model.modalities == ("img", "mic", "imu", "pressure")
    with pytest.raises(ValueError, match="shipped encoders: .*sparshx-tinier-sim"):
        load_encoder("sparshx-nonexistent")


def test_export_of_a_skin_encoder(load_script, tmp_path):
    torch.manual_seed(0)
    model = ENCODERS["skin"].build("tinier", ("skin",), "bottleneck", 0.0)
    src = ENCODERS["skin"].save(model, tmp_path / "run" / "encoder.safetensors")
    mod = load_script("export_encoder")
    out = mod.run(mod.Config(checkpoint=src.parent, out=tmp_path / "ship"))
    assert out["bytes"] < 0.6 * src.stat().st_size and 0 < out["relative_error"] < 1e-2
    loaded = load_encoder(tmp_path / "ship")
    assert type(loaded) is type(model) and all(p.dtype == torch.float32 for p in loaded.parameters())
