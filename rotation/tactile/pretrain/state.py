"""What self-distillation trains and how a pretraining run is saved: the student (encoder + head) as one module,
and checkpoints in safetensors that hold everything needed to continue bit-identically.

A checkpoint ``ckpt_<step>.safetensors`` holds the tensors ``student.*`` (encoder and head), ``teacher.*``,
the loss's state (its centers: ``center`` for Sparsh-X's DINO, ``dino.center`` and ``ibot.center`` for
Sparsh-skin) and ``optim.<param index>.<name>`` (AdamW's moments and step counts), and
as metadata (JSON strings) the step, the optimizer's groups, the encoder's structure and the run's config. The
learning-rate, weight-decay, EMA and temperature schedules are functions of the step and the masks and drop-path
draws are seeded by it, so nothing else is needed to continue.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from rotation.tactile.models.sparshx_checkpoint import SHOW, mismatch_report
from rotation.tactile.ssl import DINOHead

FORMAT = "rotation.pretrain/1"
CHECKPOINT_GLOB = "ckpt_*.safetensors"


class SelfDistillation(nn.Module):
    """Encoder + projection head: masked views of a batch -> prototype logits per token set.

    ``forward(inputs, views)`` runs the first view alone and the other views (local views: one size per set)
    together as one batch of V - 1 copies of the inputs, and returns {set: (V, B, K)} logits of the register
    tokens.
    """

    def __init__(self, encoder: nn.Module, head: DINOHead):
        super().__init__()
        self.encoder, self.head = encoder, head

    def forward(self, inputs: Mapping[str, Tensor], views: Sequence[Mapping[str, Tensor]]) -> dict[str, Tensor]:
        _, regs = self.encoder(inputs, keep=views[0], registers=True)
        out = {n: [self.head(r)[None]] for n, r in regs.items()}  # (1, B, K)
        if len(views) > 1:
            copies = len(views) - 1
            batch = next(iter(inputs.values())).shape[0]
            rep = {m: x.repeat(copies, *([1] * (x.dim() - 1))) for m, x in inputs.items()}  # (V-1) B, ...
            keep = {n: torch.cat([v[n] for v in views[1:]], dim=0) for n in views[1]}  # ((V-1) B, K_local)
            _, regs = self.encoder(rep, keep=keep, registers=True)
            for n, r in regs.items():
                out[n].append(self.head(r).reshape(copies, batch, -1))  # (V-1, B, K)
        return {n: torch.cat(parts, dim=0) for n, parts in out.items()}


def checkpoint_path(out: Path, step: int) -> Path:
    return out / f"ckpt_{step:09d}.safetensors"


def latest_checkpoint(out: Path) -> Path | None:
    ckpts = sorted(Path(out).glob(CHECKPOINT_GLOB))
    return ckpts[-1] if ckpts else None


def save_checkpoint(out: Path, step: int, student: nn.Module, teacher: nn.Module, loss: nn.Module,
                    optimizer: torch.optim.Optimizer, meta: Mapping[str, Any], keep: int) -> Path:
    """Write the checkpoint of ``step`` atomically, then delete all but the ``keep`` newest."""
    from safetensors.torch import save_file

    tensors: dict[str, Tensor] = {}
    for prefix, module in (("student", student), ("teacher", teacher)):
        tensors.update({f"{prefix}.{k}": v.detach().cpu().contiguous().clone() for k, v in module.state_dict().items()})
    for k, v in loss.state_dict().items():  # the centers: DINO's ``center``; Sparsh-skin's dino.center, ibot.center
        tensors[k] = v.detach().cpu().clone()
    state = optimizer.state_dict()
    for idx, entries in state["state"].items():
        for name, value in entries.items():
            tensors[f"optim.{idx}.{name}"] = torch.as_tensor(value).detach().cpu().contiguous().clone()
    metadata = {"format": FORMAT, "step": str(int(step)), "param_groups": json.dumps(state["param_groups"]),
                **{k: json.dumps(v) for k, v in meta.items()}}
    path = checkpoint_path(out, step)
    tmp = path.with_suffix(".tmp")
    save_file(tensors, str(tmp), metadata=metadata)
    tmp.replace(path)  # atomic: a crash never leaves a half-written checkpoint as the latest
    for old in sorted(out.glob(CHECKPOINT_GLOB))[:-keep]:
        old.unlink()
    return path


def checkpoint_run_id(path: Path) -> str | None:
    """The run id a checkpoint records in its metadata (rotation.runs.run_id), None when it records none or cannot
    be read (its loading reports that)."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            value = json.loads((f.metadata() or {}).get("run_id", "null"))
    except (SafetensorError, OSError, ValueError):
        return None
    return value if isinstance(value, str) else None


def read_checkpoint(path: Path) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """Tensors and decoded metadata of a checkpoint (ValueError naming the file if it is not one)."""
    from safetensors import SafetensorError, safe_open
    from safetensors.torch import load_file

    try:
        with safe_open(str(path), framework="pt") as f:
            raw = f.metadata() or {}
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as err:
        raise ValueError(f"{path}: not a readable safetensors checkpoint ({err})") from None
    if raw.get("format") != FORMAT:
        raise ValueError(f"{path}: not a `rotate pretrain` checkpoint (format {raw.get('format')!r}, expected "
                         f"{FORMAT!r})")
    meta = {k: (v if k == "format" else json.loads(v)) for k, v in raw.items()}
    return tensors, meta


def _load_module(module: nn.Module, tensors: Mapping[str, Tensor], prefix: str, path: Path, what: str) -> None:
    state = {k[len(prefix) + 1:]: v for k, v in tensors.items() if k.startswith(prefix + ".")}
    missing, unexpected, shapes = mismatch_report(module.state_dict(), state)
    if missing or unexpected or shapes:
        parts = [f"{len(names)} {kind}: {', '.join(names[:SHOW])}" for kind, names in
                 (("missing", missing), ("unexpected", unexpected), ("mis-shaped", shapes)) if names]
        raise ValueError(f"{path}: the {prefix} weights do not fit {what} ({'; '.join(parts)})")
    module.load_state_dict(state, strict=True)


def load_checkpoint(path: Path, student: nn.Module, teacher: nn.Module, loss: nn.Module,
                    optimizer: torch.optim.Optimizer, encoder_meta: Mapping[str, Any], what: str) -> int:
    """Restore a run from ``path``; returns its step. The checkpoint's encoder must be the one this run builds
    (``encoder_meta``, described by ``what``), else a ValueError says what each side holds."""
    tensors, meta = read_checkpoint(path)
    if meta.get("encoder") != encoder_meta:
        raise ValueError(f"{path} holds an encoder {meta.get('encoder')}; this run builds {encoder_meta} ({what})")
    _load_module(student, tensors, "student", path, what)
    _load_module(teacher, tensors, "teacher", path, what)
    for key, center in loss.state_dict().items():
        if key not in tensors:
            raise ValueError(f"{path}: no {key} (a checkpoint of another objective)")
        if tensors[key].shape != center.shape:
            raise ValueError(f"{path}: {key} of shape {tuple(tensors[key].shape)}, this run has "
                             f"{tuple(center.shape)} (another head size or token sets)")
    loss.load_state_dict({key: tensors[key] for key in loss.state_dict()}, strict=True)
    state: dict[int, dict[str, Tensor]] = {}
    for key, value in tensors.items():
        if key.startswith("optim."):
            _, idx, name = key.split(".", 2)
            state.setdefault(int(idx), {})[name] = value
    groups = meta["param_groups"]
    try:
        optimizer.load_state_dict({"state": state, "param_groups": groups})
    except ValueError as err:
        raise ValueError(f"{path}: optimizer state does not fit this run ({err})") from None
    return int(meta["step"])
