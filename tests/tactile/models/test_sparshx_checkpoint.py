"""Sparsh-X checkpoints: strict loading of released-name state dicts, clear mismatch errors, `rotate encoder-info`."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from rotation.cli import main as rotate
from rotation.tactile.models.sparshx import SparshX, SparshXConfig
from rotation.tactile.models.sparshx_checkpoint import (
    CheckpointMismatch,
    check_checkpoint,
    infer_config,
    load_pretrained,
    save_checkpoint,
)
from rotation.tactile.models.sparshx_inputs import INPUT_SHAPES, MODALITIES

FIXTURES = Path(__file__).resolve().parents[2] / "fixtures"


def shallow(seed: int = 0, **kw) -> SparshX:
    torch.manual_seed(seed)
    return SparshX(SparshXConfig(**{"size": "tinier", "unimodal_layers": 1, "fusion_layers": 2, **kw})).eval()


@pytest.fixture(scope="module")
def released(tmp_path_factory) -> tuple[Path, SparshX]:
    """A full tinier saved the way the released files are: a bare state dict in a .pth."""
    torch.manual_seed(1)
    model = SparshX(SparshXConfig(size="tinier")).eval()
    with torch.no_grad():
        model.mic_avg.fill_(2.5)  # statistics travel with the weights
        model.pos_embeds["mic"].offset.fill_(7.0)
    path = tmp_path_factory.mktemp("ckpt") / "d360_sparshx_tinier.pth"
    torch.save(model.state_dict(), path)
    return path, model


def same_model(a: SparshX, b: SparshX) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return list(sa) == list(sb) and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_released_layout_loads_strictly_with_inferred_structure(released):
    path, model = released
    loaded = load_pretrained(path)
    assert loaded.cfg == model.cfg and same_model(loaded, model)
    x = {m: torch.rand((1, *INPUT_SHAPES[m])) for m in MODALITIES}
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(loaded(x).values(), model(x).values(), strict=True))
    assert load_pretrained(path, config=SparshXConfig(size="tinier")).cfg.size == "tinier"


def test_training_checkpoint_and_our_safetensors(tmp_path, released):
    path, model = released
    training = {f"teacher_encoder.backbone.{k}": v for k, v in model.state_dict().items()}
    training |= {"student_encoder.backbone.bottleneck": torch.zeros(1), "teacher_head.mlp.0.weight": torch.zeros(2)}
    torch.save(training, tmp_path / "train.pth")
    assert same_model(load_pretrained(tmp_path / "train.pth"), model)
    torch.save({"state_dict": training, "epoch": 3}, tmp_path / "nested.pth")
    assert same_model(load_pretrained(tmp_path / "nested.pth"), model)
    variant = shallow(modalities=("img", "pressure"), fusion="vanilla", drop_path=0.1)
    save_checkpoint(variant, tmp_path / "ours.safetensors")
    again = load_pretrained(tmp_path / "ours.safetensors")
    assert again.cfg == variant.cfg and same_model(again, variant)
    assert infer_config(variant.state_dict()) == SparshXConfig(  # layer counts equal to the size's stay None
        size="tinier", modalities=("img", "pressure"), fusion="vanilla", unimodal_layers=1)


def test_mismatches_are_listed(tmp_path, released):
    path, model = released
    state = model.state_dict()
    state["blocks.0.img.attn.qkv.weights"] = state.pop("blocks.0.img.attn.qkv.weight")  # a renamed key
    torch.save(state, tmp_path / "renamed.pth")
    with pytest.raises(CheckpointMismatch) as err:
        load_pretrained(tmp_path / "renamed.pth")
    msg = str(err.value)
    assert "1 missing from the checkpoint: blocks.0.img.attn.qkv.weight" in msg
    assert "1 unexpected in the checkpoint: blocks.0.img.attn.qkv.weights" in msg
    # another modality set: everything of audio and IMU is missing, listed with counts
    with pytest.raises(CheckpointMismatch) as err:
        load_pretrained(path, config=SparshXConfig(size="tinier", modalities=("img", "pressure")))
    msg = str(err.value)
    assert re.search(r"\d+ unexpected in the checkpoint: .*\(\d+ more\)", msg) and "register_tokens" in msg
    assert "looks like: Sparsh-X tinier" in msg and "modalities img,mic,imu,pressure" in msg
    # another size: every weight has the wrong shape
    with pytest.raises(CheckpointMismatch, match=r"shape mismatches: bottleneck \(checkpoint 1x4x96, model 1x4x192\)"):
        load_pretrained(path, config=SparshXConfig(size="tiny"))
    # not a checkpoint at all
    (tmp_path / "junk.pth").write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="not a readable torch checkpoint"):
        load_pretrained(tmp_path / "junk.pth")
    torch.save({"weights": [1, 2]}, tmp_path / "list.pth")
    with pytest.raises(ValueError, match="not tensors"):
        load_pretrained(tmp_path / "list.pth")
    with pytest.raises(ValueError, match="no checkpoint file"):
        load_pretrained(tmp_path / "missing.pth")


def test_optional_tokenizer_layer_norm_follows_the_file(tmp_path):
    model = shallow(patch_layer_norm=True)
    names = set(model.state_dict())
    assert {"patch_embed.imu.layer_norm.weight", "patch_embed.pressure.layer_norm.bias"} <= names
    assert not any(k.startswith("patch_embed.img.layer_norm") for k in names)
    torch.save(model.state_dict(), tmp_path / "ln.pth")
    loaded = load_pretrained(tmp_path / "ln.pth")
    assert loaded.cfg.patch_layer_norm and same_model(loaded, model)
    # a config without the LayerNorm still loads the file: its presence is a fact of the checkpoint
    cfg, n = check_checkpoint(tmp_path / "ln.pth", SparshXConfig(size="tinier", unimodal_layers=1, fusion_layers=2))
    assert cfg.patch_layer_norm and n == len(names)
    assert not shallow().cfg.patch_layer_norm and "patch_embed.imu.layer_norm.weight" not in shallow().state_dict()


# --------------------------------------------------------------------------------------------- rotate encoder-info
def test_encoder_info_keys_of_base_are_the_released_list(capsys):
    assert rotate(["encoder-info", "--size", "base", "--keys"]) == 0
    out, err = capsys.readouterr()
    reference = [line for line in (FIXTURES / "sparshx_base_keys.txt").read_text().splitlines()
                 if line and not line.startswith("#")]
    assert out.splitlines() == reference
    assert "parameters: 341,695,488" in err


def test_encoder_info_summary_and_format(capsys):
    assert rotate(["encoder-info", "--size", "tiny", "--modalities", "imu,img"]) == 0
    out = capsys.readouterr().out
    assert "parameters: " in out and "tokens: img 196, imu 56 (252 in all), width 192" in out
    assert rotate(["encoder-info", "--size", "tinier", "--fusion", "vanilla", "--keys"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert all(re.fullmatch(r"[a-z_0-9.]+ (scalar|\d+(x\d+)*)", line) for line in lines)
    assert "imu_div scalar" in lines and "fusion_blocks.1.mlp.fc1.weight 384x96" in lines
    assert rotate(["encoder-info", "--size", "tinier", "--modalities", "img,skin"]) == 2
    assert "modalities" in capsys.readouterr().err


def test_encoder_info_checks_a_checkpoint(capsys, released):
    path, _ = released
    assert rotate(["encoder-info", "--size", "tinier", "--checkpoint", str(path)]) == 0
    assert "loads strictly, 484 tensors" in capsys.readouterr().out
    assert rotate(["encoder-info", "--size", "tiny", "--modalities", "img,mic", "--checkpoint", str(path)]) == 2
    err = capsys.readouterr().err
    assert "does not match Sparsh-X tiny" in err and "unexpected in the checkpoint" in err
    assert "shape mismatches" in err and "Traceback" not in err
