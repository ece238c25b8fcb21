"""Describe a touch encoder (Sparsh-X or Sparsh-skin): parameter count, tokens, every state-dict name, or whether a
checkpoint loads.

    rotate encoder-info --size base --modalities img,mic,imu,pressure
    rotate encoder-info --size base --keys > keys.txt        # 'name shape' per line (shape 768x6x16x16, scalar)
    rotate encoder-info --size base --checkpoint d360_sparshx_img_mic_imu_pressure_base.pth
    rotate encoder-info --encoder skin --size tiny --checkpoint runs/pretrain_skin/encoder.safetensors

The model is built on the meta device (no memory for weights, instant at any size). With ``--keys`` standard
output holds only the names, in state-dict (file) order, and the summary goes to standard error. With
``--checkpoint`` the file is loaded strictly into that structure; a mismatch is reported (missing, unexpected and
mis-shaped names, first few and counts, and what the file looks like) with exit status 2.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch

from envs.validation import check_types
from rotation.tactile.models.sparsh_skin import SparshSkin, SparshSkinConfig, load_skin
from rotation.tactile.models.sparshx import SparshX, SparshXConfig
from rotation.tactile.models.sparshx_checkpoint import check_checkpoint, shape_str


@dataclass(frozen=True)
class Config:
    encoder: Literal["sparshx", "skin"] = "sparshx"
    """Encoder kind: sparshx (a Digit 360 fingertip) or skin (Sparsh-skin, the Xela skin of the hand)."""
    size: Literal["tinier", "tiny", "small", "base"] = "base"
    """Model size (base is the released all-modality Sparsh-X; tiny the released Sparsh-skin)."""
    modalities: str = "img,mic,imu,pressure"
    """Sparsh-X: comma-separated subset of img, mic, imu, pressure."""
    fusion: Literal["bottleneck", "vanilla"] = "bottleneck"
    """Fusion layers: bottleneck tokens between per-modality blocks, or shared blocks over all tokens."""
    patch_layer_norm: bool = False
    """Build the optional LayerNorm after the IMU and pressure tokenizers (a checkpoint decides this itself)."""
    keys: bool = False
    """Print every parameter and buffer name with its shape, one per line ('name shape')."""
    checkpoint: Path | None = None
    """Checkpoint (.pth / .safetensors) to load strictly into this structure; reports success or the mismatch."""

    def __post_init__(self) -> None:
        check_types(self)
        self.model_config()  # size, modalities and fusion, checked by the model's own config
        if self.checkpoint is not None:
            object.__setattr__(self, "checkpoint", Path(self.checkpoint))
            if not self.checkpoint.is_file():
                raise ValueError(f"checkpoint: no such file: {self.checkpoint}")

    def model_config(self) -> SparshXConfig:
        return SparshXConfig(size=self.size, modalities=self.modalities, fusion=self.fusion,
                             patch_layer_norm=self.patch_layer_norm)


def key_lines(model: torch.nn.Module) -> list[str]:
    """'name shape' for every state-dict entry, in order (the released key list's format)."""
    return [f"{name} {shape_str(t.shape)}" for name, t in model.state_dict().items()]


def run(cfg: Config) -> dict:
    model_cfg = cfg.model_config() if cfg.encoder == "sparshx" else SparshSkinConfig(size=cfg.size)
    with torch.device("meta"):
        model = SparshX(model_cfg) if cfg.encoder == "sparshx" else SparshSkin(model_cfg)
    interface = model.token_interface
    tokens = ", ".join(f"{name} {count}" for name, count in interface.groups)
    summary = [
        model_cfg.describe(),
        f"parameters: {model.num_parameters():,}",
        f"tokens: {tokens} ({interface.total} in all), width {interface.width}",
        f"state-dict entries: {len(model.state_dict())} (parameters and buffers)",
    ]
    info = sys.stderr if cfg.keys else sys.stdout
    for line in summary:
        print(line, file=info)
    if cfg.keys:
        print("\n".join(key_lines(model)))
    result = {"parameters": model.num_parameters(), "tokens": dict(interface.groups), "width": interface.width,
              "entries": len(model.state_dict())}
    if cfg.checkpoint is not None:  # CheckpointMismatch is a ValueError: exit 2
        print(f"checkpoint {cfg.checkpoint}: {_check_file(cfg.checkpoint, model_cfg)}", file=info)
        result["checkpoint"] = str(cfg.checkpoint)
    return result


def _check_file(path: Path, model_cfg: SparshXConfig | SparshSkinConfig) -> str:
    """Load ``path`` strictly into the structure of ``model_cfg``; what loaded (raises on a mismatch)."""
    if isinstance(model_cfg, SparshSkinConfig):
        loaded = load_skin(path)
        if loaded.cfg.size != model_cfg.size:
            raise ValueError(f"checkpoint {path} holds {loaded.cfg.describe()}, not size {model_cfg.size}")
        return f"loads strictly, {len(loaded.state_dict())} tensors"
    used, n = check_checkpoint(path, model_cfg)
    ln = " (with the IMU/pressure tokenizer LayerNorm)" if used.patch_layer_norm else ""
    return f"loads strictly, {n} tensors{ln}"
