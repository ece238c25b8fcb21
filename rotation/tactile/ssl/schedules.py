"""Schedules, the EMA teacher update and the optimizer of self-distillation.

Every schedule is a pure function of the step (and the run's length), never a stateful scheduler object, so a
run resumed from a checkpoint continues exactly where it stopped (the counter-example: schedules that restart on
resume, as in some public pretraining code).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
from torch import nn


def cosine(step: int, total: int, start: float, end: float) -> float:
    """Half-cosine from ``start`` (step 0) to ``end`` (step >= total)."""
    if total <= 0:
        return float(end)
    progress = min(max(step / total, 0.0), 1.0)
    return float(end + (start - end) * 0.5 * (1.0 + math.cos(math.pi * progress)))


def warmup_cosine(step: int, total: int, warmup: int, peak: float, start: float, end: float) -> float:
    """Linear warm-up from ``start`` to ``peak`` over ``warmup`` steps, then a half-cosine to ``end`` at ``total``
    (DINO's learning-rate schedule; Sparsh-X: 1e-5 -> 1e-4 -> 1e-6)."""
    if step < warmup:
        return float(start + (peak - start) * step / warmup)
    return cosine(step - warmup, total - warmup, peak, end)


def ema_momentum(step: int, total: int, start: float, end: float = 1.0) -> float:
    """The teacher's EMA momentum: a cosine ramp from ``start`` to ``end`` over the run (DINO: 0.996 -> 1)."""
    return cosine(step, total, start, end)


def teacher_temperature(step: int, warmup: int, start: float = 0.04, end: float = 0.07) -> float:
    """Linear warm-up of the teacher's temperature from ``start`` to ``end`` over ``warmup`` steps, then constant
    (DINO; Sparsh-X warms 0.04 -> 0.07 over its first 10 epochs)."""
    if warmup <= 0 or step >= warmup:
        return float(end)
    return float(start + (end - start) * step / warmup)


@torch.no_grad()
def ema_update(teacher: nn.Module, student: nn.Module, momentum: float) -> None:
    """teacher = momentum teacher + (1 - momentum) student, parameter by parameter; buffers are copied (the
    input normalization statistics are the same for both). The modules must have the same structure."""
    t_params = [p for p in teacher.parameters()]
    s_params = [p.detach() for p in student.parameters()]
    if len(t_params) != len(s_params):
        raise ValueError(f"ema_update: teacher has {len(t_params)} parameters, student {len(s_params)}")
    torch._foreach_mul_(t_params, momentum)
    torch._foreach_add_(t_params, s_params, alpha=1.0 - momentum)
    for tb, sb in zip(teacher.buffers(), student.buffers(), strict=True):
        tb.copy_(sb)


def param_groups(modules: Iterable[nn.Module], weight_decay: float) -> list[dict]:
    """AdamW groups: weight decay on parameters with >= 2 dims, none on biases, norms and other 1-D (or 0-D)
    parameters (Sparsh-X, DINO). Each group carries ``base_weight_decay`` (1.0 or 0.0) to scale a schedule."""
    decay, no_decay, seen = [], [], set()
    for module in modules:
        for p in module.parameters():
            if not p.requires_grad or id(p) in seen:
                continue
            seen.add(id(p))
            (decay if p.ndim >= 2 else no_decay).append(p)
    return [{"params": decay, "weight_decay": weight_decay, "wd_scale": 1.0},
            {"params": no_decay, "weight_decay": 0.0, "wd_scale": 0.0}]


def set_hyperparameters(optimizer: torch.optim.Optimizer, lr: float, weight_decay: float) -> None:
    """Write this step's learning rate and weight decay into every group (decay only where ``wd_scale`` is 1)."""
    for group in optimizer.param_groups:
        group["lr"] = lr
        group["weight_decay"] = weight_decay * group.get("wd_scale", 1.0)
