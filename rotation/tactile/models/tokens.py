"""The token interface every touch encoder declares, and the protocol that probes and the tactile adapter consume.

A touch encoder turns one sensor sample (one Digit 360 fingertip for Sparsh-X; the whole hand's Xela skin for
Sparsh-skin) into named groups of tokens of one width::

    tokens = encoder.encode(batch)             # batch: dataset windows (rotation.data.dataset.TouchWindows)
    tokens["img"]                              # (B, 196, D) ... one (B, N_g, D) tensor per group
    encoder.token_interface                    # TokenInterface(groups=(("img", 196), ("mic", 224), ...), width=D)
    flat = encoder.token_interface.concat(tokens)   # (B, 532, D): each group layer-normed (no affine), concatenated

Consumers (attentive probes, the adapter's pooling, SSL losses over token sets) read only the interface: group
names and counts, the width, and the dict of tensors. Nothing downstream slices a concatenation by hand-copied
offsets; :meth:`TokenInterface.slices` gives each group's span. A new encoder plugs in by declaring its own
interface and implementing :class:`TouchEncoder`.

Masked views: ``forward(inputs, keep=...)`` gathers the listed patch tokens per group, so a group may come back
with fewer tokens than declared; :meth:`TokenInterface.check` accepts that with ``partial=True``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import Tensor


@dataclass(frozen=True)
class TokenInterface:
    """Named token groups of an encoder's output and their common width.

    Attributes:
        groups: ((name, count), ...) in the encoder's canonical order; ``count`` is the number of patch tokens of
            the group for a full (unmasked) input (register tokens are not counted: they are returned apart).
        width: token dimension D shared by all groups.
    """

    groups: tuple[tuple[str, int], ...]
    width: int

    def __post_init__(self) -> None:
        names = [g[0] for g in self.groups]
        if not names:
            raise ValueError("TokenInterface: at least one token group is needed")
        if len(set(names)) != len(names):
            raise ValueError(f"TokenInterface: group names repeat: {names}")
        bad = [g for g in self.groups if not (isinstance(g[0], str) and isinstance(g[1], int) and g[1] > 0)]
        if bad:
            raise ValueError(f"TokenInterface: groups must be (name, count > 0) pairs, got {bad}")
        if self.width < 1:
            raise ValueError(f"TokenInterface: width must be >= 1, got {self.width}")

    @property
    def names(self) -> tuple[str, ...]:
        """Group names in order."""
        return tuple(name for name, _ in self.groups)

    @property
    def counts(self) -> dict[str, int]:
        """Group name -> token count."""
        return dict(self.groups)

    @property
    def total(self) -> int:
        """Tokens of all groups together (e.g. 196 + 224 + 56 + 56 = 532 for Sparsh-X with four modalities)."""
        return sum(count for _, count in self.groups)

    def slices(self) -> dict[str, slice]:
        """Each group's span in the concatenation of :meth:`concat` (full, unmasked groups)."""
        out, start = {}, 0
        for name, count in self.groups:
            out[name] = slice(start, start + count)
            start += count
        return out

    def check(self, tokens: Mapping[str, Tensor], partial: bool = False) -> int:
        """Validate an encoder output against the interface; returns the batch size.

        Every group must be present (and no other), shaped (B, N, width) with one B; N must equal the declared
        count, or with ``partial=True`` (masked views) lie in 1..count.
        """
        if set(tokens) != set(self.names):
            raise ValueError(f"tokens: expected groups {list(self.names)}, got {list(tokens)}")
        batch = None
        for name, count in self.groups:
            t = tokens[name]
            ok_n = 1 <= t.shape[1] <= count if partial and t.dim() == 3 else t.dim() == 3 and t.shape[1] == count
            if t.dim() != 3 or t.shape[2] != self.width or not ok_n:
                want = f"(B, {'1..' if partial else ''}{count}, {self.width})"
                raise ValueError(f"tokens[{name!r}]: expected {want}, got {tuple(t.shape)}")
            if batch is not None and t.shape[0] != batch:
                raise ValueError(f"tokens[{name!r}]: batch {t.shape[0]} differs from the other groups' {batch}")
            batch = t.shape[0]
        return int(batch)

    def concat(self, tokens: Mapping[str, Tensor], normalize: bool = True) -> Tensor:
        """(B, sum N_g, width): the groups in interface order, each layer-normed without affine when ``normalize``
        (what Sparsh-X's downstream users do before pooling, so no group dominates by scale)."""
        self.check(tokens, partial=True)
        parts = [tokens[name] for name in self.names]
        if normalize:
            parts = [F.layer_norm(t, (self.width,)) for t in parts]
        return torch.cat(parts, dim=1)  # (B, N, D)


@runtime_checkable
class TouchEncoder(Protocol):
    """What probes, SSL and the tactile adapter need from a touch encoder (Sparsh-X, Sparsh-skin).

    - ``token_interface``: the declared groups and width (constant for a built encoder).
    - ``forward(inputs, keep=None, registers=False)``: model inputs (already preprocessed) -> {group: (B, N_g, D)};
      ``keep[g]`` (B, K_g) int64 indices of the patch tokens to keep (masked views); with ``registers=True`` a
      tuple (tokens, {group: (B, D) register token}). Sparsh-skin also takes ``token_mask`` (iBOT).
    - ``preprocess(batch)``: dataset windows (and raw sensor data, e.g. audio waveforms) -> model inputs on the
      encoder's device; other keys of the batch (labels, finger, time) are ignored.
    - ``encode(batch)``: ``forward(preprocess(batch))``, the one call a consumer of dataset batches needs.
    """

    @property
    def token_interface(self) -> TokenInterface: ...

    def forward(self, inputs: Mapping[str, Tensor], keep: Mapping[str, Tensor] | None = None,
                registers: bool = False) -> Any: ...

    def preprocess(self, batch: Mapping[str, Any]) -> dict[str, Tensor]: ...

    def encode(self, batch: Mapping[str, Any]) -> dict[str, Tensor]: ...
