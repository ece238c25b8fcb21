"""What a pretraining run logs: means over a log interval (one device sync per interval) and their TensorBoard tags."""

from __future__ import annotations

import math
import time

import torch


class StepLog:
    """Means of the logged quantities over one log interval (kept as tensors: one device sync per interval)."""

    def __init__(self) -> None:
        self.reset()
        self.t0 = time.perf_counter()

    def reset(self) -> None:
        self.loss: torch.Tensor | float = 0.0
        self.per_set: dict[str, torch.Tensor | float] = {}
        self.norm: torch.Tensor | float = 0.0
        self.n, self.samples, self.wait = 0, 0, 0.0

    def add(self, loss: torch.Tensor, per_set: dict[str, torch.Tensor], norm: torch.Tensor, samples: int) -> None:
        self.loss = self.loss + loss.detach()
        for k, v in per_set.items():
            self.per_set[k] = self.per_set.get(k, 0.0) + v.detach()
        self.norm = self.norm + norm.detach()
        self.n += 1
        self.samples += samples

    def point(self, step: int, entropy: tuple[float, float], **scalars: float) -> dict[str, float]:
        now = time.perf_counter()
        loss = float(self.loss) / self.n
        if not math.isfinite(loss):
            raise FloatingPointError(f"pretrain: the loss is {loss} at step {step}; lower --lr or raise --clip-grad")
        point = {"step": step, "loss": loss, "grad_norm": float(self.norm) / self.n,
                 "samples_per_s": self.samples / max(now - self.t0, 1e-9),
                 "data_wait_fraction": self.wait / max(now - self.t0, 1e-9),
                 "teacher_entropy": entropy[0], "teacher_batch_entropy": entropy[1], **scalars}
        point.update({f"loss_{k}": float(v) / self.n for k, v in self.per_set.items()})
        self.reset()
        self.t0 = now
        return point


def log_point(writer, point: dict[str, float]) -> None:
    """One TensorBoard point: loss/*, schedule/*, monitor/* (entropies, gradient norm), time/*."""
    step = int(point["step"])
    for key, value in point.items():
        if key == "step":
            continue
        group = "loss" if key.startswith("loss") else "time" if key in ("samples_per_s", "data_wait_fraction") \
            else "monitor" if "entropy" in key or key == "grad_norm" else "schedule"
        writer.add_scalar(f"{group}/{key}", value, global_step=step)
