"""Attentive pooling of encoder tokens and the small heads on top (the probes of Sparsh, Sparsh-X, Sparsh-skin).

``AttentivePooler``: one learned query token (trunc-normal, std 0.02) attends over the tokens in one
cross-attention block followed by an MLP, both pre-norm with residuals, and returns one vector per sample
(docs/reference/sparsh.md "Probes"). Consumers pass ``TokenInterface.concat(tokens)``: every group layer-normed (no
affine) and concatenated, so the pooler works unchanged on any encoder's token interface.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class AttentivePooler(nn.Module):
    """(B, N, D) tokens -> (B, D): a learned query cross-attends over them (one block + MLP).

    Args:
        width: token width D.
        heads: attention heads (D must be divisible by it).
        mlp_ratio: hidden width of the MLP as a multiple of D.
    """

    def __init__(self, width: int, heads: int = 4, mlp_ratio: float = 4.0):
        super().__init__()
        if width < 1 or heads < 1 or width % heads:
            raise ValueError(f"AttentivePooler: width {width} must be a positive multiple of heads {heads}")
        self.query = nn.Parameter(torch.zeros(1, 1, width))
        self.norm_q = nn.LayerNorm(width)
        self.norm_kv = nn.LayerNorm(width)
        self.attn = nn.MultiheadAttention(width, heads, batch_first=True)
        self.norm_mlp = nn.LayerNorm(width)
        hidden = int(width * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(width, hidden), nn.GELU(), nn.Linear(hidden, width))
        nn.init.trunc_normal_(self.query, std=0.02)

    def forward(self, tokens: Tensor) -> Tensor:
        q = self.query.expand(tokens.shape[0], -1, -1)  # (B, 1, D)
        kv = self.norm_kv(tokens)  # (B, N, D)
        x = q + self.attn(self.norm_q(q), kv, kv, need_weights=False)[0]  # (B, 1, D)
        x = x + self.mlp(self.norm_mlp(x))
        return x[:, 0]  # (B, D)


class ProbeHead(nn.Module):
    """Attentive pooler + MLP head: tokens (B, N, D) -> (B, outputs)."""

    def __init__(self, width: int, outputs: int, heads: int = 4, hidden: int = 256):
        super().__init__()
        self.pool = AttentivePooler(width, heads)
        self.head = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, hidden), nn.GELU(), nn.Linear(hidden, outputs))

    def forward(self, tokens: Tensor) -> Tensor:
        return self.head(self.pool(tokens))
