"""Sparsh-X: the multisensory touch encoder (image, audio, IMU, pressure of one Digit 360 fingertip).

Architecture (docs/reference/sparsh.md "Sparsh-X encoder architecture"; module names follow the released checkpoint,
docs/reference/sparshx_state_dict.md, so downloaded weights load strictly, see
rotation.tactile.models.sparshx_checkpoint)::

    inputs[m] --normalize (buffers)--> patch_embed[m] --+ pos_embeds[m]--> gather keep[m] --> [register_m ; tokens]
      layers 0..L_f-1   blocks[i][m]: each modality attends among its own tokens
      layers L_f..      fusion_blocks[j]:
                          bottleneck: y_m = block[j][m]([b ; x_m]); b = mean_m y_m[:, :4]; x_m = y_m[:, 4:]
                          vanilla:    x = block[j](cat_m x_m) (one shared block over every modality's tokens)
      norm[m] --> {m: patch tokens (B, N_m, D)} (+ {m: register token (B, D)})

Bottleneck fusion (Nagrani et al. 2021, "Attention Bottlenecks for Multimodal Fusion"): the only path between
modalities is the 4 bottleneck tokens, averaged over the modalities after every fusion layer. Vanilla fusion (the
image-only release) stores its shared blocks as ``fusion_blocks.{j}.*`` (no modality level, no ``bottleneck``).

    model = SparshX(SparshXConfig(size="tiny"))
    tokens = model.encode(batch)                      # dataset windows -> {"img": (B, 196, 192), ...}
    tokens, regs = model(model.preprocess(batch), keep={"img": idx}, registers=True)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn
from torch.utils.data import Dataset

from rotation.tactile.models.blocks import LN_EPS, Block, Float32Buffers
from rotation.tactile.models.posembed import SinCosPosEmbed
from rotation.tactile.models.sparshx_inputs import (
    INPUT_SHAPES,
    MODALITIES,
    TOKEN_GRIDS,
    fit_statistics,
    make_tokenizer,
    normalize,
    register_normalization,
    window_inputs,
)
from rotation.tactile.models.tokens import TokenInterface


@dataclass(frozen=True)
class SizeSpec:
    """Dimensions of one Sparsh-X size (docs/reference/sparsh.md)."""

    embed_dim: int
    num_heads: int
    unimodal_layers: int
    fusion_layers: int


SIZES: dict[str, SizeSpec] = {
    "tinier": SizeSpec(96, 3, 6, 2),
    "tiny": SizeSpec(192, 3, 8, 4),
    "small": SizeSpec(384, 6, 8, 4),
    "base": SizeSpec(768, 12, 8, 4),
}
"""Size name -> embed dim, heads, unimodal layers L_f, fusion layers L_b (depth = L_f + L_b)."""
FUSIONS = ("bottleneck", "vanilla")
BOTTLENECK_TOKENS = 4
"""Bottleneck tokens of the released models (docs/reference/sparsh.md)."""
MLP_RATIO = 4.0


@dataclass(frozen=True)
class SparshXConfig:
    """One Sparsh-X encoder. Validated on construction; ``modalities`` is kept in the canonical order."""

    size: str = "tiny"
    """Model size: tinier (96), tiny (192), small (384) or base (768, the released all-modality model)."""
    modalities: tuple[str, ...] = MODALITIES
    """Any non-empty subset of img, mic, imu, pressure (a comma-separated string is accepted)."""
    fusion: str = "bottleneck"
    """Fusion layers: 'bottleneck' (4 shared tokens between per-modality blocks) or 'vanilla' (shared blocks over
    all tokens concatenated)."""
    drop_path: float = 0.0
    """Stochastic depth rate of the last layer, rising linearly from 0 at the first (0.1 in pretraining)."""
    patch_layer_norm: bool = False
    """LayerNorm after the IMU and pressure tokenizers (set by the loader when a checkpoint has its keys)."""
    unimodal_layers: int | None = None
    """Override of the size's unimodal layers L_f (None: the size's)."""
    fusion_layers: int | None = None
    """Override of the size's fusion layers L_b (None: the size's; 0 = no fusion: modalities stay independent; with
    bottleneck fusion 1 fuses nothing either, :attr:`fuses`)."""

    def __post_init__(self) -> None:
        if self.size not in SIZES:
            raise ValueError(f"SparshXConfig.size: unknown size {self.size!r}; sizes: {', '.join(SIZES)}")
        mods = self.modalities
        if isinstance(mods, str):
            mods = tuple(m.strip() for m in mods.split(",") if m.strip())
        unknown = [m for m in mods if m not in MODALITIES]
        if unknown or not mods or len(set(mods)) != len(mods):
            raise ValueError(f"SparshXConfig.modalities: need a non-empty subset of {', '.join(MODALITIES)} without "
                             f"repeats, got {list(mods)}")
        object.__setattr__(self, "modalities", tuple(m for m in MODALITIES if m in mods))  # canonical order
        if self.fusion not in FUSIONS:
            raise ValueError(f"SparshXConfig.fusion: unknown fusion {self.fusion!r}; fusions: {', '.join(FUSIONS)}")
        if not 0.0 <= self.drop_path < 1.0:
            raise ValueError(f"SparshXConfig.drop_path: must be in [0, 1), got {self.drop_path}")
        for name in ("unimodal_layers", "fusion_layers"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 0):
                raise ValueError(f"SparshXConfig.{name}: must be None or an int >= 0, got {value!r}")
        if self.depth < 1:
            raise ValueError("SparshXConfig: unimodal_layers + fusion_layers must be >= 1")

    @property
    def spec(self) -> SizeSpec:
        return SIZES[self.size]

    @property
    def embed_dim(self) -> int:
        return self.spec.embed_dim

    @property
    def num_heads(self) -> int:
        return self.spec.num_heads

    @property
    def num_unimodal(self) -> int:
        """L_f: layers where each modality attends only to itself."""
        return self.spec.unimodal_layers if self.unimodal_layers is None else self.unimodal_layers

    @property
    def num_fusion(self) -> int:
        """L_b: fusion layers."""
        return self.spec.fusion_layers if self.fusion_layers is None else self.fusion_layers

    @property
    def depth(self) -> int:
        return self.num_unimodal + self.num_fusion

    @property
    def fuses(self) -> bool:
        """Whether a modality's output tokens can depend on another modality's input. Vanilla fusion: from one
        fusion layer on. Bottleneck fusion: from two on; in the first, every modality attends to the learned initial
        bottleneck tokens, the same for every input, and the mean of their outputs, which does mix the modalities,
        feeds only the next fusion layer. So one bottleneck layer is a fourth unimodal layer (tested)."""
        return self.num_fusion >= (2 if self.fusion == "bottleneck" else 1) and len(self.modalities) > 1

    @property
    def token_counts(self) -> dict[str, int]:
        """Patch tokens per modality (196, 224, 56, 56)."""
        return {m: math.prod(TOKEN_GRIDS[m]) for m in self.modalities}

    def describe(self) -> str:
        return (f"Sparsh-X {self.size} (D {self.embed_dim}, {self.num_heads} heads, {self.num_unimodal} unimodal + "
                f"{self.num_fusion} {self.fusion} fusion layers), modalities {','.join(self.modalities)}")


class SparshX(Float32Buffers):
    """The Sparsh-X encoder (see the module docstring); implements rotation.tactile.models.tokens.TouchEncoder.
    Casting it (``.to(dtype)``) casts the weights only; buffers stay float32
    (:class:`~rotation.tactile.models.blocks.Float32Buffers`).

    Parameters and buffers, in the released file order: ``bottleneck`` (1, 4, D) (bottleneck fusion with fusion
    layers only), ``register_tokens`` (M, 1, D), normalization buffers (rotation.tactile.models.sparshx_inputs),
    ``pos_embeds.{m}.{offset, frequency_bands}``, ``blocks.{i}.{m}.*``, ``fusion_blocks.{j}.{m}.*`` (vanilla:
    ``fusion_blocks.{j}.*``), ``norm.{m}``, ``patch_embed.{m}.proj`` (+ ``.layer_norm`` for IMU/pressure if asked).
    """

    def __init__(self, cfg: SparshXConfig | None = None):
        super().__init__()
        cfg = SparshXConfig() if cfg is None else cfg
        self.cfg = cfg
        d, mods = cfg.embed_dim, cfg.modalities
        if cfg.fusion == "bottleneck" and cfg.num_fusion > 0:
            self.bottleneck = nn.Parameter(torch.zeros(1, BOTTLENECK_TOKENS, d))
        self.register_tokens = nn.Parameter(torch.zeros(len(mods), 1, d))  # dim 0: modality, canonical order
        register_normalization(self, mods)
        offsets, offset = {}, 0
        for m in mods:  # running token offsets: img 0, mic 196, imu 420, pressure 476 with all four
            offsets[m], offset = offset, offset + cfg.token_counts[m]
        self.pos_embeds = nn.ModuleDict({m: SinCosPosEmbed(TOKEN_GRIDS[m], d, offsets[m]) for m in mods})
        rates = [cfg.drop_path * i / max(cfg.depth - 1, 1) for i in range(cfg.depth)]  # linear, 0 at the first
        h = cfg.num_heads

        def block(i: int) -> Block:
            return Block(d, h, MLP_RATIO, drop_path=rates[i])

        self.blocks = nn.ModuleList([nn.ModuleDict({m: block(i) for m in mods}) for i in range(cfg.num_unimodal)])
        fusion = range(cfg.num_unimodal, cfg.depth)
        if cfg.fusion == "bottleneck":
            self.fusion_blocks = nn.ModuleList([nn.ModuleDict({m: block(i) for m in mods}) for i in fusion])
        else:
            self.fusion_blocks = nn.ModuleList([block(i) for i in fusion])
        self.norm = nn.ModuleDict({m: nn.LayerNorm(d, eps=LN_EPS) for m in mods})
        self.patch_embed = nn.ModuleDict({m: make_tokenizer(m, d, cfg.patch_layer_norm) for m in mods})
        self._init_weights()

    def _init_weights(self) -> None:
        """Special initialization, all here: trunc-normal(0.02) linear weights with zero biases (ViT), bottleneck
        trunc-normal(0.02), register tokens normal(1e-6) (DINOv2 registers); LayerNorm and LayerScale keep 1/0
        and 1.0, the tokenizers PyTorch's default convolution init."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.trunc_normal_(module.weight, std=0.02)
                nn.init.zeros_(module.bias)
        if hasattr(self, "bottleneck"):
            nn.init.trunc_normal_(self.bottleneck, std=0.02)
        nn.init.normal_(self.register_tokens, std=1e-6)

    # ------------------------------------------------------------------------------------------ interface
    @property
    def modalities(self) -> tuple[str, ...]:
        return self.cfg.modalities

    @property
    def token_interface(self) -> TokenInterface:
        """Groups = modalities with their patch-token counts, width = D."""
        return TokenInterface(tuple(self.cfg.token_counts.items()), self.cfg.embed_dim)

    @property
    def device(self) -> torch.device:
        return self.register_tokens.device

    def preprocess(self, batch: Mapping[str, Any]) -> dict[str, Tensor]:
        """Dataset / env / raw windows -> float32 model inputs on the model's device (audio waveforms through the
        filterbank there); see rotation.tactile.models.sparshx_inputs.window_inputs. Float32 whatever the model's dtype:
        absolute pressure (~1000 hPa) loses its signal in bfloat16, the forward casts after normalizing."""
        return window_inputs(batch, self.modalities, self.device, torch.float32)

    def encode(self, batch: Mapping[str, Any]) -> dict[str, Tensor]:
        """``forward(preprocess(batch))``: windows -> {m: (B, N_m, D)}."""
        return self(self.preprocess(batch))

    @torch.no_grad()
    def fit_normalization(self, windows: Dataset, **kwargs: Any) -> dict[str, Tensor]:
        """Recompute the normalization buffers from ``windows`` (e.g. TouchWindows of the training sessions) and
        write them into the model; ``kwargs`` go to sparshx_inputs.fit_statistics. Returns the new values."""
        stats = fit_statistics(windows, self.modalities, **kwargs)
        self.set_normalization(stats)
        return stats

    @torch.no_grad()
    def set_normalization(self, stats: Mapping[str, Tensor]) -> None:
        """Write normalization buffers by name (shapes must match the model's)."""
        buffers = dict(self.named_buffers())
        for name, value in stats.items():
            if name not in buffers or "." in name:
                raise ValueError(f"set_normalization: {name!r} is not a normalization buffer of this model")
            value = torch.as_tensor(value)
            if value.shape != buffers[name].shape:
                raise ValueError(f"set_normalization: {name} has shape {tuple(buffers[name].shape)}, got "
                                 f"{tuple(value.shape)}")
            buffers[name].copy_(value)

    # -------------------------------------------------------------------------------------------- forward
    def _check(self, inputs: Mapping[str, Tensor], keep: Mapping[str, Tensor] | None) -> int:
        mods = self.modalities
        if not isinstance(inputs, Mapping) or set(inputs) != set(mods):
            got = list(inputs) if isinstance(inputs, Mapping) else type(inputs).__name__
            raise ValueError(f"SparshX: expected inputs for exactly the modalities {list(mods)}, got {got} "
                             "(encode()/preprocess() take dataset windows named image/audio/imu/pressure)")
        batch = None
        for m in mods:
            x, want = inputs[m], INPUT_SHAPES[m]
            if not isinstance(x, Tensor) or not x.is_floating_point() or tuple(x.shape[1:]) != want or x.dim() < 2:
                desc = f"{tuple(x.shape)} {x.dtype}" if isinstance(x, Tensor) else type(x).__name__
                raise ValueError(f"SparshX: inputs[{m!r}] must be a float tensor (B, {', '.join(map(str, want))}), "
                                 f"got {desc}")
            if batch is not None and x.shape[0] != batch:
                raise ValueError(f"SparshX: inputs[{m!r}] has batch {x.shape[0]}, the others {batch}")
            batch = x.shape[0]
        if next(iter(inputs.values())).device.type != "meta":  # meta tensors (shape checks) hold no values
            # a NaN or inf anywhere makes the sum non-finite; one small reduction per modality, one sync in all
            sums = torch.stack([inputs[m].sum(dtype=torch.float64) for m in mods]).tolist()
            bad = [m for m, s in zip(mods, sums, strict=True) if not math.isfinite(s)]
            if bad:
                raise ValueError(f"SparshX: non-finite values (NaN or inf) in the input(s) {bad}")
        for m, idx in (keep or {}).items():
            n = self.cfg.token_counts.get(m)
            if n is None:
                raise ValueError(f"SparshX: keep[{m!r}]: not a modality of this model {list(mods)}")
            if (not isinstance(idx, Tensor) or idx.dtype != torch.int64 or idx.dim() != 2 or idx.shape[0] != batch
                    or idx.shape[1] < 1):
                desc = f"{tuple(idx.shape)} {idx.dtype}" if isinstance(idx, Tensor) else type(idx).__name__
                raise ValueError(f"SparshX: keep[{m!r}] must be an int64 tensor (B={batch}, K >= 1), got {desc}")
            if idx.device.type != "meta" and (bool((idx < 0).any()) or bool((idx >= n).any())):
                raise ValueError(f"SparshX: keep[{m!r}] indices must lie in [0, {n})")
        return int(batch)

    def forward(self, inputs: Mapping[str, Tensor], keep: Mapping[str, Tensor] | None = None,
                registers: bool = False) -> dict[str, Tensor] | tuple[dict[str, Tensor], dict[str, Tensor]]:
        """Model inputs (sparshx_inputs: img, mic, imu, pressure) -> {m: patch tokens (B, N_m, D)}.

        Args:
            inputs: exactly the configured modalities, each (B, *INPUT_SHAPES[m]) float.
            keep: optional {m: (B, K_m) int64} indices of the patch tokens to keep (masked views), gathered after
                the positional embedding and before the register tokens; N_m = K_m for those modalities.
            registers: also return {m: register token (B, D)} (the DINO objective works on them).
        """
        return self.fuse(self.unimodal(inputs, keep), registers=registers)

    def unimodal(self, inputs: Mapping[str, Tensor], keep: Mapping[str, Tensor] | None = None) -> dict[str, Tensor]:
        """The first stage of :meth:`forward`: {m: (B, 1 + N_m, D)}, each modality's register token and patch tokens
        after the unimodal layers. A modality's result depends only on its own input, so an encoder restricted to
        some of these modalities (rotation.tactile.models.encoders) gives the same numbers for them."""
        bsz = self._check(inputs, keep)
        keep = keep or {}
        d, dtype = self.cfg.embed_dim, self.register_tokens.dtype
        xs: dict[str, Tensor] = {}
        for i, m in enumerate(self.modalities):
            if m == "img":  # normalization folded into the tokenizer's convolution (same result, no copy)
                x = self.patch_embed[m](inputs[m].to(dtype), self.img_avg, self.img_div)  # (B, 196, D)
            else:  # normalized in float32 (absolute pressure needs it), then the model's dtype
                x = self.patch_embed[m](normalize(self, m, inputs[m].float()).to(dtype))  # (B, N, D)
            x = x + self.pos_embeds[m]().to(x.dtype)  # (B, N, D)
            if m in keep:
                x = torch.gather(x, 1, keep[m][:, :, None].expand(-1, -1, d))  # (B, K, D)
            reg = self.register_tokens[i].expand(bsz, 1, d)  # (B, 1, D)
            xs[m] = torch.cat([reg, x], dim=1)  # (B, 1 + N, D)
        for layer in self.blocks:  # unimodal
            xs = {m: layer[m](x) for m, x in xs.items()}
        return xs

    def fuse(self, xs: Mapping[str, Tensor], registers: bool = False
             ) -> dict[str, Tensor] | tuple[dict[str, Tensor], dict[str, Tensor]]:
        """The second stage of :meth:`forward`: :meth:`unimodal`'s output for exactly this model's modalities -> the
        fusion layers, the final norms, {m: patch tokens (B, N_m, D)} (and the register tokens)."""
        if set(xs) != set(self.modalities):
            raise ValueError(f"SparshX.fuse: expected the modalities {list(self.modalities)}, got {list(xs)}")
        xs = {m: xs[m] for m in self.modalities}
        bsz = next(iter(xs.values())).shape[0]
        if self.cfg.fusion == "bottleneck" and len(self.fusion_blocks):
            nb = self.bottleneck.shape[1]
            b = self.bottleneck.expand(bsz, -1, -1)  # (B, 4, D)
            for layer in self.fusion_blocks:
                ys = {m: layer[m](torch.cat([b, x], dim=1)) for m, x in xs.items()}  # (B, 4 + 1 + N, D)
                b = self._fuse_bottleneck([y[:, :nb] for y in ys.values()])  # (B, 4, D)
                xs = {m: y[:, nb:] for m, y in ys.items()}
        elif len(self.fusion_blocks):  # vanilla: one shared block over every modality's tokens
            sizes = [x.shape[1] for x in xs.values()]
            x = torch.cat(list(xs.values()), dim=1)  # (B, sum(1 + N_m), D)
            for layer in self.fusion_blocks:
                x = layer(x)
            xs = dict(zip(xs, torch.split(x, sizes, dim=1), strict=True))
        xs = {m: self.norm[m](x) for m, x in xs.items()}
        tokens = {m: x[:, 1:] for m, x in xs.items()}  # (B, N_m, D), registers stripped
        if registers:
            return tokens, {m: x[:, 0] for m, x in xs.items()}  # (B, D)
        return tokens

    @staticmethod
    def _fuse_bottleneck(outputs: Sequence[Tensor]) -> Tensor:
        """Next layer's bottleneck: the mean over modalities of their output bottleneck tokens (B, 4, D)."""
        return torch.stack(list(outputs), dim=0).mean(dim=0)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def build(size: str = "tiny", modalities: Sequence[str] | str = MODALITIES, **kwargs: Any) -> SparshX:
    """Shorthand: ``SparshX(SparshXConfig(size, modalities, **kwargs))``."""
    mods = modalities if isinstance(modalities, str) else tuple(modalities)
    return SparshX(SparshXConfig(size=size, modalities=mods, **kwargs))
