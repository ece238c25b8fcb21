"""A frozen encoder's tokens computed once per variant: the probes of a frozen variant train on them instead of
running the encoder on every batch of every step.

A frozen encoder in eval mode maps a window to the same tokens each time it reads it (the probe's windows carry no
augmentation), so computing them once is exact: the heads see the same tokens in the same batch order as when the
encoder runs inside the step. On 2 CPU cores the encoder's forward pass is most of a frozen probe's step (Sparsh-X
tinier: 0.19 s for a batch of 32; the attentive heads' step 25-75 ms, three tasks over 532 tokens), so a frozen
variant of 2,000 steps at three label budgets costs one pass over the windows instead of 6,000.

The tokens are held in memory, float32, (windows, tokens, width): Sparsh-X tinier's 532 tokens of width 96 take
204 kB a window, 3.4 GB for 16,500 windows. Past ``Config.token_cache_gb`` the probes fall back to the encoder in
the step. Sequences of windows (the temporal skin tasks) always run the encoder in the step.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset

from rotation.interrupt import ignore_stop_signals
from rotation.tactile.loading import to_device
from rotation.tactile.runtime import autocast

TOKENS = "frozen_tokens"
"""Batch key of precomputed tokens (B, N, D); a batch holding it skips the encoder."""
_KEPT = ("time", "session")
"""Per-window fields the evaluation reads besides the labels."""


class FrozenTokens(Dataset):
    """Windows as their frozen tokens, with the labels and fields the probes read."""

    def __init__(self, tokens: Tensor, fields: dict[str, Tensor]):
        if any(len(v) != len(tokens) for v in fields.values()):
            raise ValueError("FrozenTokens: every field needs one row per window")
        self.tokens, self.fields = tokens, fields

    def __len__(self) -> int:
        return len(self.tokens)

    def __getitem__(self, i: int) -> dict[str, Tensor]:
        return {TOKENS: self.tokens[i], **{k: v[i] for k, v in self.fields.items()}}


@torch.no_grad()
def frozen_tokens(encoder: nn.Module, data: Dataset, labels: tuple[str, ...], batch_size: int, num_workers: int,
                  device: torch.device, bf16: bool, bar=None) -> FrozenTokens:
    """Every window of ``data`` through the frozen ``encoder`` (eval mode), in order, kept on the CPU."""
    encoder.eval()
    loader = DataLoader(data, batch_size=batch_size, shuffle=False, num_workers=num_workers,
                        worker_init_fn=ignore_stop_signals)
    tokens: list[Tensor] = []
    fields: dict[str, list[Tensor]] = {}
    for batch in loader:
        batch = to_device(batch, device)
        with autocast(device, bf16):
            out = encoder.token_interface.concat(encoder(encoder.preprocess(batch)))
        tokens.append(out.float().cpu())
        for key in (*labels, *_KEPT):
            if key in batch:
                fields.setdefault(key, []).append(batch[key].cpu())
        if bar is not None:
            bar.update(len(out))
    return FrozenTokens(torch.cat(tokens), {k: torch.cat(v) for k, v in fields.items()})


def fits(nbytes: int, limit_gb: float) -> bool:
    """Whether ``nbytes`` of tokens stay within ``limit_gb`` (0 or less: never cache)."""
    return limit_gb > 0 and nbytes <= limit_gb * 1e9


__all__ = ["TOKENS", "FrozenTokens", "fits", "frozen_tokens"]
