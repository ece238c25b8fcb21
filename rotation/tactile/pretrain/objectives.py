"""What each encoder's self-distillation computes in one step: its views, the student and teacher forwards, the
loss, and what is updated after the optimizer step. The training loop (rotation.tactile.pretrain.job) is shared and
sees an encoder's objective only through :class:`Objective`.

- ``sparshx`` (docs/reference/sparsh.md "Sparsh-X self-supervised pretraining"): per modality one global and
  ``mask.num_local`` local block views (rotation.tactile.ssl.masking.sample_views); the teacher sees the global
  view, the student all; DINO on the register tokens, summed over the student's views and the modalities.
- ``skin`` (docs/reference/sparsh.md "Sparsh-skin", DINOv2): ``skin.num_global`` global and ``skin.num_local`` local
  blocks over the taxel order (sample_multi_views); the teacher sees the global views, the student all, with
  iBOT masks in its global views; loss = DINO (register tokens, cross-view pairs) + ``ibot_weight`` x iBOT
  (masked tokens) + ``koleo_weight`` x KoLeo (the student's global-view register tokens, per view).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor, nn

from rotation.tactile.pretrain.state import SelfDistillation
from rotation.tactile.ssl import (
    DINOHead,
    DINOLoss,
    IBOTLoss,
    ViewMaskConfig,
    Views,
    koleo_loss,
    sample_multi_views,
    sample_views,
)


class Objective(Protocol):
    """One encoder kind's self-distillation step, split where the loop needs it split:

    ``views`` (before the batch reaches the device), ``forward`` (under autocast: teacher without gradient, then
    the student, the module the optimizer and DDP see), ``loss`` (float32, outside autocast) -> (total, terms
    logged as ``loss_<term>``), ``update_centers`` (after the optimizer and EMA steps), ``monitor`` (the
    teacher's distributions for the collapse monitors, at log points)."""

    def build(self, encoder: nn.Module, head: DINOHead, prototypes: int) -> tuple[nn.Module, nn.Module]: ...

    def views(self, grids: Mapping[str, tuple[int, ...]], batch: int, rng: np.random.Generator,
              device: torch.device) -> Any: ...

    def forward(self, model: nn.Module, teacher: nn.Module, inputs: Mapping[str, Tensor], views: Any) -> Any: ...

    def loss(self, loss_fn: nn.Module, out: Any, teacher_temp: float) -> tuple[Tensor, dict[str, Tensor]]: ...

    def update_centers(self, loss_fn: nn.Module, out: Any) -> None: ...

    def monitor(self, loss_fn: nn.Module, out: Any, teacher_temp: float) -> dict[str, Tensor]: ...


# ----------------------------------------------------------------------------------------------- Sparsh-X
class SparshXObjective:
    """DINO on block-masked views, one global view per token set (see the module docstring)."""

    def __init__(self, cfg: Any) -> None:
        self.cfg = cfg

    def build(self, encoder: nn.Module, head: DINOHead, prototypes: int) -> tuple[nn.Module, nn.Module]:
        names = encoder.token_interface.names
        return SelfDistillation(encoder, head), DINOLoss(names, prototypes, self.cfg.student_temp,
                                                          self.cfg.center_momentum)

    def views(self, grids, batch, rng, device):
        return sample_views(grids, batch, self.cfg.mask, rng, device)

    def forward(self, model, teacher, inputs, views):
        with torch.no_grad():
            t_logits = {n: x[0] for n, x in teacher(inputs, views[:1]).items()}  # (B, K)
        return {"teacher": t_logits, "student": model(inputs, views)}  # student: (V, B, K)

    def loss(self, loss_fn, out, teacher_temp):
        return loss_fn(out["student"], out["teacher"], teacher_temp)

    def update_centers(self, loss_fn, out):
        loss_fn.update_center(out["teacher"])

    def monitor(self, loss_fn, out, teacher_temp):
        return loss_fn.teacher_probs(out["teacher"], teacher_temp)


# ----------------------------------------------------------------------------------------------- Sparsh-skin
@dataclass(frozen=True)
class SkinObjectiveConfig(ViewMaskConfig):
    """Sparsh-skin's views (global / local blocks over the taxel order, iBOT masks) and loss weights."""

    ibot_weight: float = 0.5
    """Weight of the iBOT masked-token loss (docs/reference/sparsh.md: x 1/2); 0 turns it off."""
    koleo_weight: float = 0.1
    """Weight of the KoLeo regularizer (docs/reference/sparsh.md, DINOv2: 0.1); 0 turns it off."""

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("ibot_weight", "koleo_weight"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value <= 100.0):
                raise ValueError(f"skin.{name} must be a finite number in [0, 100], got {value!r}")


def _repeat(inputs: Mapping[str, Tensor], copies: int) -> dict[str, Tensor]:
    """Each input repeated ``copies`` times along the batch: (copies B, ...), copy-major."""
    return {m: x.repeat(copies, *([1] * (x.dim() - 1))) for m, x in inputs.items()}


def _stack_views(views: list[Mapping[str, Tensor]]) -> dict[str, Tensor]:
    """[{set: (B, K)}] x V -> {set: (V B, K)}, view-major (matches :func:`_repeat`)."""
    return {n: torch.cat([v[n] for v in views], dim=0) for n in views[0]}


class SkinDistillation(nn.Module):
    """Encoder + projection head for DINO + iBOT + KoLeo (the student; the teacher is an EMA copy).

    ``forward(inputs, views)`` (the student) returns ``cls`` {set: (G + L, B, K)} register-token logits of the
    global then local views, ``patch`` {set: (M, K)} logits of the tokens it saw masked (all samples and global
    views, view-major), and ``embed`` {set: (G, B, D)} its global-view register tokens (for KoLeo).
    :meth:`teacher_forward` returns the teacher's ``cls`` {set: (G, B, K)} and ``patch`` at the same tokens,
    seen unmasked.
    """

    def __init__(self, encoder: nn.Module, head: DINOHead):
        super().__init__()
        self.encoder, self.head = encoder, head

    def _globals(self, inputs: Mapping[str, Tensor], views: Views, masked: bool) -> tuple[dict, dict, dict, int, int]:
        g = len(views.globals)
        batch = next(iter(inputs.values())).shape[0]
        masks = _stack_views(views.masks)  # {set: (G B, K_g)}
        tokens, regs = self.encoder(_repeat(inputs, g), keep=_stack_views(views.globals), registers=True,
                                    **({"token_mask": masks} if masked else {}))
        return tokens, regs, masks, g, batch

    def forward(self, inputs: Mapping[str, Tensor], views: Views) -> dict[str, dict[str, Tensor]]:
        tokens, regs, masks, g, batch = self._globals(inputs, views, masked=True)
        cls = {n: [self.head(r).reshape(g, batch, -1)] for n, r in regs.items()}  # (G, B, K)
        patch = {n: self.head(tokens[n][masks[n]]) for n in tokens}  # (M, K)
        embed = {n: r.reshape(g, batch, -1) for n, r in regs.items()}  # (G, B, D)
        if views.locals:
            copies = len(views.locals)
            _, regs = self.encoder(_repeat(inputs, copies), keep=_stack_views(views.locals), registers=True)
            for n, r in regs.items():
                cls[n].append(self.head(r).reshape(copies, batch, -1))  # (L, B, K)
        return {"cls": {n: torch.cat(parts, dim=0) for n, parts in cls.items()}, "patch": patch, "embed": embed}

    @torch.no_grad()
    def teacher_forward(self, inputs: Mapping[str, Tensor], views: Views) -> dict[str, dict[str, Tensor]]:
        tokens, regs, masks, g, batch = self._globals(inputs, views, masked=False)
        return {"cls": {n: self.head(r).reshape(g, batch, -1) for n, r in regs.items()},  # (G, B, K)
                "patch": {n: self.head(tokens[n][masks[n]]) for n in tokens}}  # (M, K)


class SkinLoss(nn.Module):
    """DINO's and iBOT's losses with their own centers (state-dict entries ``dino.center``, ``ibot.center``)."""

    def __init__(self, names: tuple[str, ...], prototypes: int, student_temp: float, center_momentum: float):
        super().__init__()
        self.dino = DINOLoss(names, prototypes, student_temp, center_momentum)
        self.ibot = IBOTLoss(names, prototypes, student_temp, center_momentum)


class SkinObjective:
    """DINO + iBOT + KoLeo on DINOv2-style views (see the module docstring)."""

    def __init__(self, cfg: Any) -> None:
        self.cfg = cfg
        self.skin: SkinObjectiveConfig = cfg.skin

    def build(self, encoder: nn.Module, head: DINOHead, prototypes: int) -> tuple[nn.Module, nn.Module]:
        names = encoder.token_interface.names
        return SkinDistillation(encoder, head), SkinLoss(names, prototypes, self.cfg.student_temp,
                                                         self.cfg.center_momentum)

    def views(self, grids, batch, rng, device):
        return sample_multi_views(grids, batch, self.skin, rng, device)

    def forward(self, model, teacher, inputs, views):
        return {"teacher": teacher.teacher_forward(inputs, views), "student": model(inputs, views)}

    def loss(self, loss_fn, out, teacher_temp):
        s, t = out["student"], out["teacher"]
        dino, _ = loss_fn.dino.views_loss(s["cls"], t["cls"], teacher_temp)
        ibot, _ = loss_fn.ibot(s["patch"], t["patch"], teacher_temp)
        koleo = torch.stack([koleo_loss(e[v]) for e in s["embed"].values() for v in range(e.shape[0])]).sum()
        total = dino + self.skin.ibot_weight * ibot + self.skin.koleo_weight * koleo
        return total, {"dino": dino, "ibot": ibot, "koleo": koleo}

    def update_centers(self, loss_fn, out):
        loss_fn.dino.update_center(out["teacher"]["cls"])
        loss_fn.ibot.update_center(out["teacher"]["patch"])

    def monitor(self, loss_fn, out, teacher_temp):
        return loss_fn.dino.teacher_probs(out["teacher"]["cls"], teacher_temp)


OBJECTIVES = {"sparshx": SparshXObjective, "skin": SkinObjective}
"""Encoder kind (rotation.tactile.models.encoders.ENCODERS) -> its objective class (built from the run's Config)."""
