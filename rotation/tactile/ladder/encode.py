"""The ladder's rungs that read rendered windows: stage 2 (simple stream features), stage 3 (a frozen encoder's
tokens, pooled per modality by their mean and their maximum) and stage 4 (the same encoder structure trained end to
end from random weights on the samples' targets, the baseline frozen tokens must beat at small label budgets).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.data import default_collate

from envs.constants import FINGERS
from envs.sensors.digit360 import NUM_FIELDS
from envs.sensors.digit360_image import render_frame
from rotation.tactile.ladder.fit import tercile_of
from rotation.tactile.ladder.samples import (
    MODALITIES,
    SESSION_TARGETS,
    HandSamples,
    history_mean,
    slip_history,
    stream_features,
)
from rotation.tactile.models.encoders import fresh_like

GROUP_MODALITY = {"img": "image", "mic": "audio", "imu": "imu", "pressure": "pressure"}
"""Sparsh-X token group -> the modality it reads."""


def references(samples: HandSamples) -> dict[tuple[int, int], np.ndarray]:
    """(session, fingertip) -> (3, H, W) float image of that sensor without contact (what a lab captures before
    grasping: the background, lighting and markers of the physical sensor)."""
    out = {}
    rest = np.zeros(NUM_FIELDS, np.float32)
    for s in np.unique(samples.session):
        model = samples.windows.sensor_model(int(s))
        for f in range(len(FINGERS)):
            out[(int(s), f)] = render_frame(rest, 0, 0, f, model).transpose(2, 0, 1).astype(np.float32) / 255.0
    return out


def rendered_features(samples: HandSamples, encoder: nn.Module | None, batch: int = 8,
                      progress: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
    """Stage 2 (``stream/<modality>``) and, with an encoder, stage 3 (``tokens/<modality>``) features of every
    sample: (M, 4 x F) arrays, the four fingertips' concatenated. Renders each window once."""
    refs = references(samples)
    feats: dict[str, list[np.ndarray]] = {}
    for lo in range(0, len(samples), batch):
        rows = range(lo, min(lo + batch, len(samples)))
        windows = [[samples.windows[int(samples.items[m, f])] for f in range(len(FINGERS))] for m in rows]
        for m, per_finger in zip(rows, windows, strict=True):
            simple = [stream_features(w, refs[(int(samples.session[m]), f)]) for f, w in enumerate(per_finger)]
            for mod in MODALITIES:
                feats.setdefault(f"stream/{mod}", []).append(np.concatenate([s[mod] for s in simple]))
        if encoder is not None:
            flat = [w for per_finger in windows for w in per_finger]  # sample-major, fingertip-minor
            pooled = pooled_tokens(encoder, flat)  # group -> (B 4, D)
            for group, v in pooled.items():
                v = v.reshape(len(windows), -1)  # (B, 4 D)
                feats.setdefault(f"tokens/{GROUP_MODALITY.get(group, group)}", []).extend(list(v))
        if progress is not None:
            progress(len(rows))
    return {k: np.asarray(v, np.float64) for k, v in feats.items()}


def pool(tokens: torch.Tensor) -> torch.Tensor:
    """(B, N, D) tokens of one group -> (B, 2 D): layer-normed (the token interface's view), then their mean and
    their maximum over the N tokens. The mean alone dilutes what a few tokens carry (an imprint covers a handful of
    the image's 196 patches); the maximum keeps it, as an attentive probe's query would."""
    t = F.layer_norm(tokens.float(), tokens.shape[-1:])
    return torch.cat([t.mean(1), t.amax(1)], -1)


@torch.no_grad()
def pooled_tokens(encoder: nn.Module, windows: Sequence[dict]) -> dict[str, np.ndarray]:
    """Group -> (B, 2 D): each token group pooled by :func:`pool`."""
    encoder.eval()
    tokens = encoder.encode(default_collate(list(windows)))
    return {g: pool(t).cpu().numpy() for g, t in tokens.items()}


# ------------------------------------------------------------------------------------------ stage 4: end to end
class HandHead(nn.Module):
    """An encoder (trained) over the four fingertips' windows, its tokens pooled as the frozen rung's (:func:`pool`)
    and concatenated, one linear output per target."""

    def __init__(self, encoder: nn.Module, outputs: dict[str, int]):
        super().__init__()
        self.encoder = encoder
        width = 2 * encoder.token_interface.width * len(encoder.token_interface.names) * len(FINGERS)
        self.heads = nn.ModuleDict({k: nn.Linear(width, n) for k, n in outputs.items()})

    def forward(self, windows: Sequence[dict]) -> dict[str, torch.Tensor]:
        tokens = self.encoder.encode(default_collate(list(windows)))
        pooled = torch.cat([pool(t) for t in tokens.values()], -1)
        pooled = pooled.reshape(len(windows) // len(FINGERS), -1)
        return {k: h(pooled) for k, h in self.heads.items()}


def train_end_to_end(reference: nn.Module, samples: HandSamples, rows: np.ndarray, y: dict[str, np.ndarray],
                     kinds: dict[str, str], classes: int, steps: int, batch: int, lr: float, seed: int,
                     progress: Callable[[int], None] | None = None) -> HandHead:
    """Train a fresh encoder of ``reference``'s structure (its input statistics kept: data facts, not learned) and
    the heads on samples ``rows`` for ``steps`` Adam steps; regression targets standardized, the tercile by cross
    entropy, slip by binary cross entropy."""
    torch.manual_seed(seed)
    fresh = fresh_like(reference)
    outputs = {k: (classes if kinds[k] == "accuracy" else y[k].shape[1]) for k in y}
    model = HandHead(fresh, outputs).train()
    stats = {k: (y[k][rows].mean(0), np.maximum(y[k][rows].std(0), 1e-6)) for k in y if kinds[k] == "r2"}
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=0.05)
    rng = np.random.default_rng([seed, 0x653265])
    for _ in range(steps):
        pick = rng.choice(rows, size=min(batch, len(rows)), replace=len(rows) < batch)
        windows = [samples.windows[int(samples.items[m, f])] for m in pick for f in range(len(FINGERS))]
        out = model(windows)
        loss = torch.zeros(())
        for k, pred in out.items():
            t = torch.as_tensor(y[k][pick], dtype=torch.float32)
            if kinds[k] == "accuracy":
                loss = loss + F.cross_entropy(pred, t[:, 0].long())
            elif kinds[k] == "f1":
                loss = loss + F.binary_cross_entropy_with_logits(pred, t)
            else:
                mean, std = (torch.as_tensor(v, dtype=torch.float32) for v in stats[k])
                loss = loss + F.mse_loss(pred, (t - mean) / std)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if progress is not None:
            progress(1)
    model.eval()
    model.stats = stats  # type: ignore[attr-defined]
    return model


@torch.no_grad()
def predict_end_to_end(model: HandHead, samples: HandSamples, rows: np.ndarray, kinds: dict[str, str],
                       batch: int = 8, history: float = 0.0,
                       friction_edges: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Predictions of every target on samples ``rows`` in the targets' units (classes as integers, slip 0/1); the
    object's properties from the outputs averaged over ``history`` seconds (:func:`history_mean`; ``rows`` should
    hold whole sessions). With ``friction_edges`` friction is read as the frozen rungs read it: its outputs weighted
    by the model's own slip probability (the mean over the fingertips, at least SLIP_FLOOR) and the tercile cut from
    that estimate at the edges."""
    raw: dict[str, list[np.ndarray]] = {}
    for lo in range(0, len(rows), batch):
        pick = rows[lo:lo + batch]
        windows = [samples.windows[int(samples.items[m, f])] for m in pick for f in range(len(FINGERS))]
        for k, pred in model(windows).items():
            raw.setdefault(k, []).append(pred.numpy().astype(np.float64))
    raw_all = {k: np.concatenate(parts) for k, parts in raw.items()}
    session, frame = samples.session[rows], samples.frame[rows]
    out = {}
    for k, p in raw_all.items():
        if k in SESSION_TARGETS:
            if friction_edges is not None and k == "friction":
                sliding = 1.0 / (1.0 + np.exp(-raw_all["slip"]))  # (M, 4) probabilities
                # one hand-level output: all its columns weighted by the fingertips' mean slip probability
                p = slip_history(p, np.zeros(p.shape[1], np.int64), sliding.mean(1, keepdims=True), session, frame,
                                 history)
            else:
                p = history_mean(p, session, frame, history)
        if kinds[k] == "accuracy":
            p = p.argmax(1)[:, None].astype(np.float64)
        elif kinds[k] == "f1":
            p = (p > 0).astype(np.float64)
        else:
            mean, std = model.stats[k]  # type: ignore[attr-defined]
            p = p * std + mean
        out[k] = p
    if friction_edges is not None:
        out["friction_tercile"] = tercile_of(out["friction"], friction_edges)
    return out
