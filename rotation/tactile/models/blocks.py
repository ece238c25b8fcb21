"""Pre-norm ViT blocks with the parameter names of the released touch encoders (DINOv2 layout).

``Block`` holds ``norm1``, ``attn.qkv``, ``attn.proj``, ``ls1.gamma``, ``norm2``, ``mlp.fc1``, ``mlp.fc2``,
``ls2.gamma``: exactly the 14 state-dict names per block of the released Sparsh-X checkpoint
(docs/reference/sparshx_state_dict.md), so a downloaded checkpoint loads strictly. LayerNorm eps 1e-6, qkv with bias,
exact (erf) GELU, MLP ratio 4, LayerScale initialized to 1.0, stochastic depth on both residual branches.
Attention runs through ``F.scaled_dot_product_attention`` (fused kernels on CPU and GPU; scale head_dim^-0.5).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

LN_EPS = 1e-6
"""LayerNorm epsilon of the released blocks."""


class LayerScale(nn.Module):
    """Per-channel scale of a residual branch (CaiT), ``gamma`` initialized to ``init``."""

    def __init__(self, dim: int, init: float = 1.0):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init)))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class DropPath(nn.Module):
    """Stochastic depth: drops a sample's whole residual branch with probability ``p`` in training (rescaled)."""

    def __init__(self, p: float = 0.0):
        super().__init__()
        self.p = float(p)

    def forward(self, x: Tensor) -> Tensor:
        if self.p == 0.0 or not self.training:
            return x
        keep = 1.0 - self.p
        mask = x.new_empty((x.shape[0],) + (1,) * (x.dim() - 1)).bernoulli_(keep)  # (B, 1, 1)
        return x * mask / keep

    def extra_repr(self) -> str:
        return f"p={self.p}"


class Attention(nn.Module):
    """Multi-head self-attention over all tokens (no mask; with ``causal`` each token attends to itself and the
    tokens before it), fused qkv projection with bias."""

    def __init__(self, dim: int, num_heads: int, causal: bool = False):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"Attention: dim {dim} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.causal = causal
        self.qkv = nn.Linear(dim, 3 * dim, bias=True)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        b, n, d = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, d // self.num_heads)  # (B, N, 3, H, hd)
        q, k, v = qkv.permute(2, 0, 3, 1, 4).unbind(0)  # 3 x (B, H, N, hd)
        out = F.scaled_dot_product_attention(q, k, v, is_causal=self.causal)  # (B, H, N, hd), scale hd^-0.5
        return self.proj(out.transpose(1, 2).reshape(b, n, d))  # (B, N, D)


class Mlp(nn.Module):
    """fc1 -> exact GELU -> fc2."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    """``x + drop(ls1(attn(norm1(x))))`` then ``x + drop(ls2(mlp(norm2(x))))``; (B, N, D) -> (B, N, D)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0, drop_path: float = 0.0,
                 layer_scale: float = 1.0, causal: bool = False):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=LN_EPS)
        self.attn = Attention(dim, num_heads, causal)
        self.ls1 = LayerScale(dim, layer_scale)
        self.norm2 = nn.LayerNorm(dim, eps=LN_EPS)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, layer_scale)
        self.drop_path = DropPath(drop_path)

    def forward(self, x: Tensor) -> Tensor:
        if self.training and self.drop_path.p > 0.0:
            x = x + self.drop_path(self.ls1(self.attn(self.norm1(x))))
            return x + self.drop_path(self.ls2(self.mlp(self.norm2(x))))
        # the same without stochastic depth, scale and residual in one op (fewer passes over the tokens)
        x = torch.addcmul(x, self.attn(self.norm1(x)), self.ls1.gamma)
        return torch.addcmul(x, self.mlp(self.norm2(x)), self.ls2.gamma)


class Float32Buffers(nn.Module):
    """A module whose floating-point buffers stay float32 when it is cast: ``.to(dtype)`` / ``.half()`` cast the
    weights only, while the buffers still move with the model. Input statistics and frequency bands are buffers,
    and 8 significant bits (bfloat16) lose the token positions and the normalization of absolute signals."""

    def _apply(self, fn: Any, recurse: bool = True) -> Float32Buffers:
        before = dict(self.named_buffers())
        super()._apply(fn, recurse)
        for name, buf in list(self.named_buffers()):
            old = before.get(name)
            if old is not None and old.is_floating_point() and buf.dtype != old.dtype:
                owner, _, attr = name.rpartition(".")
                self.get_submodule(owner)._buffers[attr] = old.to(device=buf.device)
        return self
