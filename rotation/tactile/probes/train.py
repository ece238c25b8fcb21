"""Training and scoring the probes of one (variant, label budget): attentive heads over a frozen encoder's tokens,
or over encoders trained end to end with them.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from rotation.interrupt import ignore_stop_signals
from rotation.tactile.loading import step_loader, to_device
from rotation.tactile.models.encoders import encoder_kind, fresh_like, kind_of, load_encoder
from rotation.tactile.models.pooling import ProbeHead
from rotation.tactile.probes.config import MODALITY_VARIANTS, Config
from rotation.tactile.probes.data import (
    Task,
)
from rotation.tactile.probes.skin import (
    TemporalProbeHead,
)
from rotation.tactile.probes.tokens import TOKENS
from rotation.tactile.runtime import (
    Processes,
    autocast,
)


# ------------------------------------------------------------------------------------------------- models
class Probes(nn.Module):
    """One probe head per task over a frozen shared encoder, or each over its own trained encoder (e2e).

    Temporal tasks read (B, S, ...) sequences: the encoder sees the B S windows, each head gets their tokens."""

    def __init__(self, encoder: nn.Module, frozen: bool, tasks: dict[str, Task], cfg: Config):
        super().__init__()
        self.frozen, self.tasks = frozen, tuple(tasks)
        self.temporal = any(t.temporal for t in tasks.values())
        width = encoder.token_interface.width
        head = TemporalProbeHead if self.temporal else ProbeHead
        self.heads = nn.ModuleDict({name: head(width, t.outputs, cfg.pooler_heads, cfg.head_hidden)
                                    for name, t in tasks.items()})
        if frozen:
            self.encoder = encoder.eval().requires_grad_(False)
        else:
            self.encoders = nn.ModuleDict({name: copy.deepcopy(encoder).train() for name in tasks})
        self.__dict__["reference"] = encoder  # preprocess and token interface (not a submodule: no training)

    def train(self, mode: bool = True) -> Probes:
        super().train(mode)
        if self.frozen:
            self.encoder.eval()  # a frozen encoder stays in eval mode (no drop path)
        return self

    def forward(self, inputs: dict[str, Tensor]) -> dict[str, Tensor]:
        interface = self.reference.token_interface
        seq = None
        if self.temporal:  # (B, S, ...) -> (B S, ...): every window through the encoder
            seq = next(iter(inputs.values())).shape[1]
            inputs = {k: v.flatten(0, 1) for k, v in inputs.items()}

        def head(name: str, flat: Tensor) -> Tensor:
            return self.heads[name](flat, seq) if seq is not None else self.heads[name](flat)

        if self.frozen:
            if TOKENS in inputs:  # computed once beforehand (rotation.tactile.probes.tokens)
                flat = inputs[TOKENS]
            else:
                with torch.no_grad():
                    flat = interface.concat(self.encoder(inputs))  # (B [S], N, D)
            return {t: head(t, flat) for t in self.tasks}
        return {t: head(t, interface.concat(self.encoders[t](inputs))) for t in self.tasks}

    def trainable(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]


def variant_encoder(variant: str, pretrained: nn.Module, cfg: Config, device: torch.device) -> nn.Module:
    kind = encoder_kind(kind_of(pretrained))
    if variant in ("pretrained", "all"):
        return pretrained
    if variant in MODALITY_VARIANTS and variant != "all":
        groups = MODALITY_VARIANTS[variant]
        missing = [g for g in groups if g not in pretrained.token_interface.names]
        if missing:
            raise ValueError(f"variant {variant}: the encoder of {cfg.checkpoint} has no {missing[0]} tokens "
                             f"({list(pretrained.token_interface.names)}); drop the variant")
        return kind.restrict(pretrained, groups)
    if variant == "image_only":
        if cfg.image_checkpoint is not None:
            enc = load_encoder(cfg.image_checkpoint, device=device)
            if tuple(enc.token_interface.names) != ("img",):
                raise ValueError(f"--image-checkpoint {cfg.image_checkpoint}: expected an image-only encoder, got "
                                 f"token groups {list(enc.token_interface.names)}")
            return enc
        if "img" not in pretrained.token_interface.names:
            raise ValueError(f"variant image_only: the encoder of {cfg.checkpoint} has no image tokens "
                             f"({list(pretrained.token_interface.names)}); drop the variant or pass --image-checkpoint")
        return kind.restrict(pretrained, ("img",))
    # e2e: the same structure from scratch, with the checkpoint's input statistics (data facts, not learned)
    torch.manual_seed(cfg.seed)
    return fresh_like(pretrained).to(device)


# ------------------------------------------------------------------------------------------------ training
def _inputs(probes: Probes, batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """The probes' inputs of a batch: its precomputed tokens as they are, or its windows preprocessed."""
    return batch if TOKENS in batch else probes.reference.preprocess(batch)


def _targets(batch: dict[str, Tensor], task: Task, cfg: Config) -> Tensor:
    return task.target(batch[task.label].float(), cfg.slip_threshold)


def train_probes(probes: Probes, data: Dataset, tasks: dict[str, Task], cfg: Config,
                  stats: dict[str, tuple[Tensor, Tensor]], pos_weight: float, device: torch.device, bf16: bool,
                  bar: tqdm, writer: Any, tag: str) -> None:
    opt = torch.optim.Adam(probes.trainable(), lr=cfg.lr)
    loader = step_loader(data, cfg.batch_size, Processes(), cfg.seed, 0, cfg.steps, cfg.num_workers,
                         device.type == "cuda")
    probes.train()
    pw = torch.tensor([pos_weight], device=device)
    for step, batch in enumerate(loader):
        batch = to_device(batch, device)
        inputs = _inputs(probes, batch)
        with autocast(device, bf16):
            preds = probes(inputs)
        losses = {}
        for name, task in tasks.items():
            y = _targets(batch, task, cfg)
            p = preds[name].float()
            if task.classes:
                losses[name] = F.cross_entropy(p, y[:, 0].long())
            elif task.classify:
                losses[name] = F.binary_cross_entropy_with_logits(p, y, pos_weight=pw)
            else:
                mean, std = stats[name]
                fn = F.smooth_l1_loss if task.loss == "smooth_l1" else F.mse_loss
                losses[name] = fn(p, (y - mean) / std)
        loss = torch.stack(list(losses.values())).sum()  # independent parameters: each probe sees its own gradient
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        bar.update(1)
        if writer is not None and (step % 50 == 0 or step + 1 == cfg.steps):
            for t, v in losses.items():
                writer.add_scalar(f"{tag}/{t}_loss", float(v.detach()), global_step=step)


@torch.no_grad()
def evaluate(probes: Probes, data: Dataset, tasks: dict[str, Task], cfg: Config,
              stats: dict[str, tuple[Tensor, Tensor]], device: torch.device, bf16: bool
              ) -> tuple[dict[str, dict[str, float]], dict[str, dict[str, np.ndarray]]]:
    """Metrics per task on ``data``, and for temporal tasks the traces of the last window of every sequence
    (``pred``, ``true`` (N, outputs), ``time`` (N,) s, ``session`` (N,)) for the plots over time; for multi-class
    tasks the confusion matrix instead (``confusion`` (classes, classes): rows true, columns predicted)."""
    probes.eval()
    loader = DataLoader(data, batch_size=cfg.batch_size, shuffle=False, num_workers=cfg.num_workers,
                        worker_init_fn=ignore_stop_signals)
    preds: dict[str, list[np.ndarray]] = {t: [] for t in tasks}
    targets: dict[str, list[np.ndarray]] = {t: [] for t in tasks}
    times, sessions = [], []
    for batch in loader:
        batch = to_device(batch, device)
        with autocast(device, bf16):
            out = probes(_inputs(probes, batch))
        for name, task in tasks.items():
            p = out[name].float()
            if task.classes:
                p = p.argmax(dim=-1, keepdim=True).float()
            elif task.classify:
                p = (p > 0).float()
            else:
                mean, std = stats[name]
                p = p * std + mean
            preds[name].append(p.cpu().numpy())
            targets[name].append(_targets(batch, task, cfg).cpu().numpy())
        times.append(batch["time"].cpu().numpy())
        sessions.append(batch["session"].cpu().numpy())
    scores, traces = {}, {}
    for name, task in tasks.items():
        p, t = np.concatenate(preds[name]), np.concatenate(targets[name])
        scores[name] = task.metrics(p.reshape(-1, p.shape[-1]), t.reshape(-1, t.shape[-1]))
        if task.classes:
            confusion = np.zeros((task.classes, task.classes), np.int64)
            np.add.at(confusion, (t.reshape(-1).astype(np.int64), p.reshape(-1).astype(np.int64)), 1)
            traces[name] = {"confusion": confusion}
        if task.temporal:  # (N, S, out): the last window of each sequence has the whole history
            traces[name] = {"pred": p[:, -1], "true": t[:, -1], "time": np.concatenate(times)[:, -1],
                            "session": np.concatenate(sessions)}
    return scores, traces
