"""Sparsh-skin: the touch encoder of the Xela skin covering the whole hand (368 taxels, one sample = the hand).

Architecture (docs/reference/sparsh.md "Sparsh-skin")::

    window (B, 10, 368, 6) raw counts + positions --preprocess: - baseline, raw outside 20k..60k -> 0-->
    inputs["skin"] (B, 10, 368, 6)  10 frames at 100 Hz x 368 taxels x [3 magnetic (counts), 3 position (m)]
      --normalize per channel (buffers skin_avg, skin_div)--> per taxel a Conv1d over the 10 frames (kernel 10)
      --> (B, 368, D) one token per taxel --gather keep--> masked taxels -> mask_token (iBOT)
      --> + taxel_embed[taxel] + type_embed[taxel_type[taxel]] --> [register ; tokens] --> blocks --> norm
      --> {"skin": patch tokens (B, N, D)} (+ {"skin": register token (B, D)})

One token group, ``skin`` with 368 tokens, so probes and the tactile adapter read it through the same
rotation.tactile.models.tokens.TokenInterface as Sparsh-X. A token covers all 10 frames of its taxel, so a view that
keeps a taxel keeps it across time. The iBOT mask token replaces a taxel's convolution output before the taxel
and type embeddings are added (as in DINOv2): the student knows where the taxel it must predict is. Taxel order
and types: envs.sensors.xela (``PADS``, ``TAXEL_TYPE``).

    model = SparshSkin(SparshSkinConfig(size="tiny"))
    tokens = model.encode(batch)                 # windows (rotation.data.skin, env obs, Xela reader) -> (B, 368, 192)
    tokens, regs = model(model.preprocess(batch), keep={"skin": idx}, token_mask={"skin": m}, registers=True)
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset, Subset

from envs.sensors.xela import NUM_TAXELS, REST, TAXEL_TYPE, TAXEL_TYPES, VALID_RANGE, WINDOW
from rotation.configs import from_jsonable, to_jsonable
from rotation.interrupt import ignore_stop_signals
from rotation.tactile.models.blocks import LN_EPS, Block, Float32Buffers
from rotation.tactile.models.sparshx_checkpoint import (
    SHOW,
    CheckpointMismatch,
    mismatch_report,
    read_safetensors,
    stored_tensors,
)
from rotation.tactile.models.tokens import TokenInterface

GROUP = "skin"
"""The encoder's one token group (and model input name)."""
CHANNELS = 6
"""Channels per taxel and frame: 3 magnetic axes, 3 position coordinates (docs/reference/sparsh.md)."""
MLP_RATIO = 4.0
FILE_FORMAT = "sparsh_skin"
"""``format`` metadata of a saved Sparsh-skin encoder (safetensors)."""
_STD_FLOOR = 1e-6


@dataclass(frozen=True)
class SkinSize:
    """Dimensions of one Sparsh-skin size (docs/reference/sparsh.md)."""

    embed_dim: int
    depth: int
    num_heads: int


SIZES: dict[str, SkinSize] = {
    "tinier": SkinSize(96, 8, 3),
    "tiny": SkinSize(192, 8, 3),
    "small": SkinSize(384, 12, 6),
    "base": SkinSize(768, 12, 12),
}
"""Size name -> width, layers, heads (the released Sparsh-skin is ``tiny``)."""


@dataclass(frozen=True)
class SparshSkinConfig:
    """One Sparsh-skin encoder. Validated on construction."""

    size: str = "tiny"
    """Model size: tinier (96), tiny (192, the released size), small (384) or base (768)."""
    drop_path: float = 0.0
    """Stochastic depth rate of the last layer, rising linearly from 0 at the first."""

    def __post_init__(self) -> None:
        if self.size not in SIZES:
            raise ValueError(f"SparshSkinConfig.size: unknown size {self.size!r}; sizes: {', '.join(SIZES)}")
        if isinstance(self.drop_path, bool) or not isinstance(self.drop_path, int | float) \
                or not 0.0 <= self.drop_path < 1.0:
            raise ValueError(f"SparshSkinConfig.drop_path: must be in [0, 1), got {self.drop_path!r}")

    @property
    def spec(self) -> SkinSize:
        return SIZES[self.size]

    @property
    def embed_dim(self) -> int:
        return self.spec.embed_dim

    @property
    def input_shape(self) -> tuple[int, int, int]:
        """Per-sample model input: (frames, taxels, channels) = (10, 368, 6)."""
        return WINDOW, NUM_TAXELS, CHANNELS

    def describe(self) -> str:
        s = self.spec
        return (f"Sparsh-skin {self.size} (D {s.embed_dim}, {s.num_heads} heads, {s.depth} layers), "
                f"{NUM_TAXELS} taxels x {WINDOW} frames")


class SparshSkin(Float32Buffers):
    """The Sparsh-skin encoder (see the module docstring); implements rotation.tactile.models.tokens.TouchEncoder.

    Parameters: ``register_token`` (1, 1, D), ``mask_token`` (1, 1, D), ``taxel_embed`` (368, D), ``type_embed``
    (3, D), ``patch_embed.proj`` (Conv1d 6 -> D, kernel 10), ``blocks.{i}.*``, ``norm``. Buffers: ``skin_avg`` and
    ``skin_div`` (6,) (input normalization, fitted on sessions), ``taxel_type`` (368,) int64 (the layout).
    """

    def __init__(self, cfg: SparshSkinConfig | None = None):
        super().__init__()
        cfg = SparshSkinConfig() if cfg is None else cfg
        self.cfg = cfg
        d, depth = cfg.embed_dim, cfg.spec.depth
        self.register_token = nn.Parameter(torch.zeros(1, 1, d))
        self.mask_token = nn.Parameter(torch.zeros(1, 1, d))
        self.taxel_embed = nn.Parameter(torch.zeros(NUM_TAXELS, d))
        self.type_embed = nn.Parameter(torch.zeros(len(TAXEL_TYPES), d))
        self.register_buffer("skin_avg", torch.zeros(CHANNELS))
        self.register_buffer("skin_div", torch.ones(CHANNELS))
        self.register_buffer("taxel_type", torch.as_tensor(TAXEL_TYPE, dtype=torch.int64).clone())
        self.patch_embed = nn.Module()
        self.patch_embed.proj = nn.Conv1d(CHANNELS, d, kernel_size=WINDOW, stride=WINDOW)
        rates = [cfg.drop_path * i / max(depth - 1, 1) for i in range(depth)]  # linear, 0 at the first
        self.blocks = nn.ModuleList([Block(d, cfg.spec.num_heads, MLP_RATIO, drop_path=r) for r in rates])
        self.norm = nn.LayerNorm(d, eps=LN_EPS)
        self._init_weights()

    def _init_weights(self) -> None:
        """Special initialization, all here: trunc-normal(0.02) linear weights with zero biases and embeddings
        (ViT), register token normal(1e-6) (DINOv2 registers), mask token zero (DINOv2); LayerNorm and LayerScale
        keep 1/0 and 1.0, the tokenizer PyTorch's default convolution init."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.trunc_normal_(module.weight, std=0.02)
                nn.init.zeros_(module.bias)
        nn.init.trunc_normal_(self.taxel_embed, std=0.02)
        nn.init.trunc_normal_(self.type_embed, std=0.02)
        nn.init.normal_(self.register_token, std=1e-6)
        nn.init.zeros_(self.mask_token)

    # ------------------------------------------------------------------------------------------ interface
    @property
    def token_interface(self) -> TokenInterface:
        return TokenInterface(((GROUP, NUM_TAXELS),), self.cfg.embed_dim)

    @property
    def device(self) -> torch.device:
        return self.register_token.device

    def preprocess(self, batch: Mapping[str, Any]) -> dict[str, Tensor]:
        """Raw skin windows -> float32 model inputs on the model's device (:func:`skin_inputs`): ``skin``
        (B, [S,] 10, 368, 6) raw counts + positions (rotation.data.skin.SkinWindows, the env's `skin`
        observation, rotation.hardware.xela.reader) and ``xela_baseline`` (B, 368, 3) if known. Other keys are
        ignored."""
        return skin_inputs(batch, self.device)

    def encode(self, batch: Mapping[str, Any]) -> dict[str, Tensor]:
        """``forward(preprocess(batch))``: windows -> {"skin": (B, 368, D)}."""
        return self(self.preprocess(batch))

    @torch.no_grad()
    def fit_normalization(self, windows: Dataset, max_windows: int = 2048, batch_size: int = 32,
                          num_workers: int = 0, seed: int = 0) -> dict[str, Tensor]:
        """Per-channel mean and standard deviation of the 6 input channels over (a seeded random subset of)
        ``windows``, written into ``skin_avg`` / ``skin_div``; returns them. Sums run in float64."""
        n = len(windows)  # type: ignore[arg-type]
        if n == 0:
            raise ValueError("fit_normalization: no windows")
        pick = np.sort(np.random.default_rng(seed).permutation(n)[: min(n, max_windows)])
        loader = DataLoader(Subset(windows, pick.tolist()), batch_size=batch_size, num_workers=num_workers,
                            worker_init_fn=ignore_stop_signals)
        count = 0
        total, squares = torch.zeros(CHANNELS, dtype=torch.float64), torch.zeros(CHANNELS, dtype=torch.float64)
        for batch in loader:
            x = skin_inputs(batch, "cpu")[GROUP].to(torch.float64).reshape(-1, CHANNELS)  # (B 10 368, 6)
            count += x.shape[0]
            total += x.sum(0)
            squares += x.square().sum(0)
        mean = total / count
        std = (squares / count - mean.square()).clamp_min(0.0).sqrt().clamp_min(_STD_FLOOR)
        self.skin_avg.copy_(mean.float())
        self.skin_div.copy_(std.float())
        return {"skin_avg": self.skin_avg.clone(), "skin_div": self.skin_div.clone()}

    # -------------------------------------------------------------------------------------------- forward
    def _check(self, inputs: Mapping[str, Tensor], keep: Mapping[str, Tensor] | None,
               token_mask: Mapping[str, Tensor] | None) -> int:
        if not isinstance(inputs, Mapping) or set(inputs) != {GROUP}:
            got = list(inputs) if isinstance(inputs, Mapping) else type(inputs).__name__
            raise ValueError(f"SparshSkin: expected inputs {{'skin': (B, 10, 368, 6)}}, got {got} (encode() and "
                             "preprocess() take raw windows: skin, xela_baseline)")
        x, want = inputs[GROUP], self.cfg.input_shape
        if not isinstance(x, Tensor) or not x.is_floating_point() or x.dim() != 4 or tuple(x.shape[1:]) != want:
            desc = f"{tuple(x.shape)} {x.dtype}" if isinstance(x, Tensor) else type(x).__name__
            raise ValueError(f"SparshSkin: inputs['skin'] must be a float tensor (B, {', '.join(map(str, want))}), "
                             f"got {desc}")
        batch = x.shape[0]
        if x.device.type != "meta" and not math.isfinite(float(x.sum(dtype=torch.float64))):
            raise ValueError("SparshSkin: non-finite values (NaN or inf) in the input 'skin'")
        kept = NUM_TAXELS
        for name, idx in (keep or {}).items():
            if name != GROUP or not isinstance(idx, Tensor) or idx.dtype != torch.int64 or idx.dim() != 2 \
                    or idx.shape[0] != batch or idx.shape[1] < 1:
                desc = f"{tuple(idx.shape)} {idx.dtype}" if isinstance(idx, Tensor) else type(idx).__name__
                raise ValueError(f"SparshSkin: keep must be {{'skin': int64 (B={batch}, K >= 1)}}, got "
                                 f"{name!r}: {desc}")
            if idx.device.type != "meta" and (bool((idx < 0).any()) or bool((idx >= NUM_TAXELS).any())):
                raise ValueError(f"SparshSkin: keep['skin'] indices must lie in [0, {NUM_TAXELS})")
            kept = idx.shape[1]
        for name, m in (token_mask or {}).items():
            if name != GROUP or not isinstance(m, Tensor) or m.dtype != torch.bool or tuple(m.shape) != (batch, kept):
                desc = f"{tuple(m.shape)} {m.dtype}" if isinstance(m, Tensor) else type(m).__name__
                raise ValueError(f"SparshSkin: token_mask must be {{'skin': bool (B={batch}, {kept})}} over the kept "
                                 f"tokens, got {name!r}: {desc}")
        return int(batch)

    def forward(self, inputs: Mapping[str, Tensor], keep: Mapping[str, Tensor] | None = None,
                registers: bool = False, token_mask: Mapping[str, Tensor] | None = None
                ) -> dict[str, Tensor] | tuple[dict[str, Tensor], dict[str, Tensor]]:
        """Model inputs {"skin": (B, 10, 368, 6)} -> {"skin": patch tokens (B, N, D)}.

        Args:
            inputs: see :meth:`preprocess`.
            keep: optional {"skin": (B, K) int64} taxels to keep (a masked view); N = K.
            registers: also return {"skin": register token (B, D)}.
            token_mask: optional {"skin": (B, N) bool} over the kept tokens: True = replaced by the mask token
                (iBOT); the output keeps those positions (the student's prediction of the hidden taxels).
        """
        bsz = self._check(inputs, keep, token_mask)
        d, dtype = self.cfg.embed_dim, self.register_token.dtype
        x = (inputs[GROUP].float() - self.skin_avg) / self.skin_div  # (B, T, N, C), float32
        b, t, n, c = x.shape
        x = x.permute(0, 2, 3, 1).reshape(b * n, c, t).to(dtype)  # (B N, C, T): each taxel's channels over time
        x = self.patch_embed.proj(x).reshape(b, n, d)  # (B N, D, 1) -> (B, N, D)
        embed = self.taxel_embed + self.type_embed[self.taxel_type]  # (N, D)
        if keep and GROUP in keep:
            idx = keep[GROUP]  # (B, K)
            x = torch.gather(x, 1, idx[:, :, None].expand(-1, -1, d))  # (B, K, D)
            embed = embed[idx]  # (B, K, D)
        if token_mask and GROUP in token_mask:  # always through where(): the mask token stays in the graph
            x = torch.where(token_mask[GROUP][:, :, None], self.mask_token.to(x.dtype), x)
        x = x + embed.to(x.dtype)
        x = torch.cat([self.register_token.expand(bsz, 1, d), x], dim=1)  # (B, 1 + N, D)
        for block in self.blocks:
            x = block(x)
        x = self.norm(x)
        tokens = {GROUP: x[:, 1:]}  # (B, N, D)
        if registers:
            return tokens, {GROUP: x[:, 0]}  # (B, D)
        return tokens

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def skin_inputs(batch: Mapping[str, Any], device: torch.device | str = "cpu") -> dict[str, Tensor]:
    """Batched raw skin windows (tensors or numpy arrays) -> {"skin": (B, [S,] 10, 368, 6) float32} on ``device``.

    ``batch["skin"]`` (..., 10, 368, 6): [..., :3] raw counts, [..., 3:] taxel positions (m). The magnetic
    channels become ``raw - baseline``, and 0 where the raw value lies outside VALID_RANGE (docs/reference/sparsh.md);
    the baseline is ``batch["xela_baseline"]`` (B, 368, 3) or (368, 3), else REST (the nominal rest reading: a
    sensor's per-taxel offsets then stay in the signal). Positions pass unchanged.
    """
    if "skin" not in batch:
        raise ValueError(f"skin windows: expected 'skin' (B, 10, 368, 6) raw counts + positions, got {sorted(batch)}")
    x = torch.as_tensor(batch["skin"]).to(device=device, dtype=torch.float32)
    if x.dim() < 4 or tuple(x.shape[-3:]) != (WINDOW, NUM_TAXELS, CHANNELS):
        raise ValueError(f"skin windows: 'skin' must be (B, [S,] {WINDOW}, {NUM_TAXELS}, {CHANNELS}), "
                         f"got {tuple(x.shape)}")
    raw, pos = x[..., :3], x[..., 3:]
    base = batch.get("xela_baseline")
    if base is None:
        base = torch.full((NUM_TAXELS, 3), REST, device=device)
    base = torch.as_tensor(base).to(device=device, dtype=torch.float32)
    if base.dim() == 3:  # (B, 368, 3) -> (B, 1, ..., 368, 3) against (B, [S,] 10, 368, 3)
        base = base.reshape(base.shape[0], *([1] * (raw.dim() - 3)), NUM_TAXELS, 3)
    valid = (raw >= VALID_RANGE[0]) & (raw <= VALID_RANGE[1])
    signal = torch.where(valid, raw - base, torch.zeros_like(raw))
    return {GROUP: torch.cat([signal, pos], dim=-1)}


# ------------------------------------------------------------------------------------------------- files
def save_skin(model: SparshSkin, path: str | Path, weights_dtype: torch.dtype | None = None) -> Path:
    """Write the encoder's state dict as safetensors with its config in the metadata; ``weights_dtype`` (e.g.
    torch.float16, for a shipped file): rotation.tactile.models.sparshx_checkpoint.stored_tensors."""
    from safetensors.torch import save_file

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors = stored_tensors(model, weights_dtype)
    save_file(tensors, str(path), metadata={"format": FILE_FORMAT, "config": json.dumps(to_jsonable(model.cfg))})
    return path


def load_skin(path: str | Path, drop_path: float | None = None, device: torch.device | str = "cpu") -> SparshSkin:
    """A Sparsh-skin encoder from a file of :func:`save_skin`, loaded strictly (CheckpointMismatch, a ValueError,
    lists the missing, unexpected and mis-shaped names)."""
    path = Path(path)
    state, meta = read_safetensors(path)
    if meta.get("format") != FILE_FORMAT or "config" not in meta:
        raise ValueError(f"{path}: not a Sparsh-skin encoder (format {meta.get('format')!r}, expected {FILE_FORMAT!r})")
    cfg = from_jsonable(SparshSkinConfig, json.loads(meta["config"]))
    if drop_path is not None:
        cfg = SparshSkinConfig(size=cfg.size, drop_path=drop_path)
    with torch.device("meta"):
        model = SparshSkin(cfg)
    missing, unexpected, shapes = mismatch_report(model.state_dict(), state)
    if missing or unexpected or shapes:
        parts = [f"{len(names)} {what}: {', '.join(names[:SHOW])}" for what, names in
                 (("missing", missing), ("unexpected", unexpected), ("mis-shaped", shapes)) if names]
        raise CheckpointMismatch(f"{path} does not match {cfg.describe()} ({'; '.join(parts)})")
    model = model.to_empty(device=device)
    model.load_state_dict(state, strict=True)
    return model
