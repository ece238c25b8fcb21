"""Demonstrations as training samples: each action step of each demonstration (rotation.jobs.demos) with its camera
frame, proprioception, the fingertips' touch embeddings and the chunk of actions that follows, each action as the
env's step executes it (:data:`LIMITS`).

Touch: the window of each fingertip ending at the newest 30 fps frame at or before the step's time (what the
closed-loop policy reads then: envs.held_hand.TouchHistory). Through a frozen encoder it is embedded once and the
embeddings are cached beside the run (OUT/touch_<encoder>_<modalities>.npz, named by the demonstrations' files and
sizes, so a second policy on the same demonstrations and encoder reuses them); an end-to-end policy renders its
batches' windows as it trains (:func:`touch_rows`, :func:`window_batch`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from envs.constants import FINGERS
from envs.insertion import InsertionConfig, clip_action
from rotation.data.session_reader import SessionReader

IMAGE_HZ = 30.0
LIMITS = InsertionConfig()
"""The env whose step limits (``max_step``, ``max_turn``) the recorded actions are clipped to before a policy learns
them: sessions keep the expert's raw label, which can be far outside what a step executes (in the demonstrations of
experiments/insertion 9% of the labels move more than 3 mm on an axis and 16% turn more than 2 degrees, up to 0.59
rad; in a DAgger round's states more), and those outliers would set the actions' standardization and the loss."""


def proprio_of(wrist: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """The policy's proprioception: the wrist target's offset (7) and the joints (16)."""
    return np.concatenate([np.asarray(wrist, np.float32), np.asarray(joints, np.float32)], axis=-1)


class Demos(Dataset):
    """Samples of demonstration sessions ``paths`` for a policy predicting ``chunk`` actions (see the module
    docstring); ``touch``: per-step fingertip embeddings (T_total, 4, D) in step order, or None."""

    def __init__(self, paths: list[Path], chunk: int, touch: np.ndarray | None = None) -> None:
        self.paths, self.chunk = list(paths), int(chunk)
        images, proprio, actions, times, starts = [], [], [], [], []
        for path in self.paths:
            with SessionReader(path) as r:
                images.append(np.asarray(r.stream("camera/wrist").data, np.uint8))
                proprio.append(proprio_of(r.stream("wrist/pose").data, r.stream("joints/position").data))
                actions.append(clip_action(LIMITS, r.stream("actions/wrist").data).astype(np.float32))
                times.append(np.asarray(r.stream("actions/wrist").timestamps))
            starts.append(sum(len(a) for a in actions[:-1]))
        if not actions or not sum(len(a) for a in actions):
            raise ValueError("no demonstration steps in the sessions")
        self.images, self.proprio = np.concatenate(images), np.concatenate(proprio)
        self.actions, self.times = np.concatenate(actions), times
        self.episode_of = np.concatenate([np.full(len(a), i) for i, a in enumerate(actions)])
        self.ends = np.array([s + len(a) for s, a in zip(starts, actions, strict=True)])
        self.touch = None if touch is None else np.asarray(touch, np.float32)
        if self.touch is not None and len(self.touch) != len(self.actions):
            raise ValueError(f"{len(self.touch)} touch embeddings for {len(self.actions)} steps")

    def __len__(self) -> int:
        return len(self.actions)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        end = int(self.ends[self.episode_of[i]])
        rows = np.arange(i, i + self.chunk)
        valid = rows < end
        chunk = self.actions[np.minimum(rows, end - 1)]  # past the episode's end: its last action, masked out
        out = {"image": torch.from_numpy(self.images[i]), "proprio": torch.from_numpy(self.proprio[i]),
               "actions": torch.from_numpy(chunk), "mask": torch.from_numpy(valid)}
        if self.touch is not None:
            out["touch"] = torch.from_numpy(self.touch[i])
        return out


def touch_rows(paths: list[Path], skin: bool = False) -> tuple[Any, np.ndarray]:
    """The demonstrations' fingertip windows (rotation.data.dataset.TouchWindows) and, for every action step in
    :class:`Demos`' order, the indices (T_total, 4) of its four fingertips' windows (module docstring); with
    ``skin``, the skin's windows (rotation.data.skin.SkinWindows) and the index (T_total, 1) of the window ending
    at the newest skin sample at or before each step."""
    if skin:
        return _skin_rows(paths)
    from rotation.data.dataset import TouchWindows

    windows = TouchWindows(paths)
    where = {(int(s), int(f), int(e)): k for k, (s, f, e) in enumerate(windows.index)}  # (session, finger, frame)
    rows = []
    for s, path in enumerate(paths):
        with SessionReader(path) as r:
            t = np.asarray(r.stream("actions/wrist").timestamps)
        rows += [[where[(s, f, int(np.floor(ti * IMAGE_HZ + 1e-6)))] for f in range(len(FINGERS))] for ti in t]
    return windows, np.asarray(rows, np.int64).reshape(-1, len(FINGERS))


def _skin_rows(paths: list[Path]) -> tuple[Any, np.ndarray]:
    from rotation.data.skin import SkinWindows

    windows = SkinWindows(paths, labels=(), stride=1)
    rows = []
    for s, path in enumerate(paths):
        mine = np.flatnonzero(windows.index[:, 0] == s)
        with SessionReader(path) as r:
            t = np.asarray(r.stream("actions/wrist").timestamps)
        k = np.searchsorted(windows.end_times[mine], t + 1e-6, side="right") - 1
        if len(t) and k.min() < 0:
            raise ValueError(f"{path}: a step at {t[np.argmin(k)]:.3f} s comes before the skin's first full window")
        rows += list(mine[k])
    return windows, np.asarray(rows, np.int64).reshape(-1, 1)


TOUCH_KEYS = ("image", "audio", "imu", "pressure", "skin", "xela_baseline")
"""The encoders' input tensors a window may carry (Sparsh-X's four, or the skin's window and baseline)."""


def window_batch(windows: Any, rows: np.ndarray) -> dict[str, torch.Tensor]:
    """The loader-format tensors of the windows ``rows`` (any shape: flattened in order), stacked."""
    samples = [windows[int(k)] for k in np.asarray(rows).reshape(-1)]
    return {key: torch.stack([smp[key] for smp in samples]) for key in TOUCH_KEYS if key in samples[0]}


def touch_embeddings(paths: list[Path], encoder: str, modalities: str, cache_dir: Path, progress: bool = True
                     ) -> np.ndarray:
    """(T_total, F, D) embeddings of every step's windows (module docstring; F = 4 fingertips, or 1 for the skin),
    cached in ``cache_dir``."""
    from rotation.il.touch import TouchEmbedder

    ident = json.dumps([encoder, modalities, [(str(p), p.stat().st_size) for p in paths]])
    cache = cache_dir / f"touch_{Path(encoder).name}_{modalities}_{hashlib.sha256(ident.encode()).hexdigest()[:12]}.npz"
    if cache.is_file():
        return np.load(cache)["touch"]
    embedder = TouchEmbedder(encoder, modalities)
    windows, rows = touch_rows(paths, skin=embedder.skin)
    out = np.zeros((len(rows), rows.shape[1], embedder.width), np.float32)
    batch = 16
    for a in tqdm(range(0, len(rows), batch), desc="touch embeddings", unit="batch", disable=not progress):
        x = window_batch(windows, rows[a:a + batch])
        out[a:a + batch] = embedder.embed(x).reshape(-1, rows.shape[1], embedder.width).numpy()
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, touch=out)
    tmp.replace(cache)
    return out
