"""The data side of `rotate probe`: train/test windows split by session, labels read without rendering, nested label
budgets, target standardization and the mean-predictor baselines.

Every task needs windows of one kind: single windows (instantaneous tasks) or sequences of windows (temporal
tasks, Sparsh-skin); :class:`ProbeData` holds one kind for one split of the sessions.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from rotation.data.dataset import PER_FINGERTIP
from rotation.data.session_reader import SessionReader
from rotation.data.window_cache import CachedWindows
from rotation.tactile.loading import open_encoder_windows

_TIME_EPS = 1e-6


@dataclass(frozen=True)
class Task:
    """One probe task: which label, how many outputs, its loss and its metrics."""

    label: str
    """Dataset label the target comes from."""
    outputs: int
    classify: bool
    """Binary classification (BCE, balanced accuracy) instead of regression (on standardized targets)."""
    target: Callable[[Tensor, float], Tensor]
    """(label batch, slip threshold) -> (B, outputs) float targets ((B, S, outputs) for temporal tasks)."""
    metrics: Callable[[np.ndarray, np.ndarray], dict[str, float]]
    """(predictions, targets) (N, outputs), in physical units / {0, 1} -> {metric: value}."""
    temporal: bool = False
    """Reads sequences of windows and predicts at every window (Sparsh-skin's temporal decoders)."""
    loss: str = "mse"
    """Regression loss on standardized targets: 'mse' or 'smooth_l1'."""
    classes: int = 0
    """Multi-class classification over this many classes (cross-entropy, arg-max predictions; the target is the
    class id, (B, 1)); 0: regression or ``classify``."""


def window_labels(ds: Dataset, name: str) -> np.ndarray:
    """Label ``name`` of every window of a TouchWindows, CachedWindows or SkinWindows, read without rendering
    (N, ...), or (N, S, ...) for sequences of skin windows."""
    if hasattr(ds, "labels_array"):
        return ds.labels_array(name)  # type: ignore[attr-defined]
    if isinstance(ds, CachedWindows):
        parts = [np.load(s / f"label_{name}.npy") for s in ds.shards]
        return np.concatenate([p for p in parts if len(p)]).astype(np.float32)  # empty shards: no windows
    out = []
    for s, path in enumerate(ds.paths):  # type: ignore[attr-defined]
        rows = np.flatnonzero(ds.index[:, 0] == s)  # type: ignore[attr-defined]
        if not len(rows):
            continue
        with SessionReader(path) as r:
            st = r.stream(f"labels/{name}")
            j = np.searchsorted(st.timestamps, ds.end_times[rows] + _TIME_EPS, side="right") - 1  # type: ignore[attr-defined]
            value = np.asarray(st.data)[j]
        if name in PER_FINGERTIP:
            value = value[np.arange(len(rows)), ds.index[rows, 1]]  # type: ignore[attr-defined]
        out.append(value.astype(np.float32))
    return np.concatenate(out)


@dataclass
class ProbeData:
    """The windows (or sequences) of one kind for the train and test sessions."""

    train: Dataset
    test: Dataset
    train_sessions: list[Path]
    test_sessions: list[Path]
    train_labels: dict[str, np.ndarray]
    """Label name -> (N_train, ...) labels of every training sample (read without rendering)."""


def open_probe_data(encoder: str, train_paths: Sequence[Path], test_paths: Sequence[Path], cache: Path | None,
                    fingers: Sequence[str], stride: int, labels: tuple[str, ...], sequence: int | None) -> ProbeData:
    """Train and test samples of ``encoder`` (``sequence`` windows per sample for temporal tasks)."""
    train = open_encoder_windows(encoder, train_paths, cache, fingers, stride, labels=labels, build=False,
                                 sequence=sequence)
    test = open_encoder_windows(encoder, test_paths, cache, fingers, stride, labels=labels, build=False,
                                sequence=sequence)
    if len(test) == 0 or len(train) == 0:
        need = "1.12 s of touch" if encoder == "sparshx" else f"{(sequence or 1) * 0.1:.1f} s of skin"
        raise ValueError(f"probe: no {'sequences' if sequence else 'windows'} in the "
                         f"{'test' if len(test) == 0 else 'training'} sessions (each needs at least {need})")
    return ProbeData(train, test, list(train_paths), list(test_paths),
                     {name: window_labels(train, name) for name in labels})


def budget_rows(data: ProbeData, budget: float, seed: int) -> tuple[np.ndarray, int]:
    """Training samples of the first max(1, round(budget n)) training sessions in a seeded order (nested budgets),
    and that number of sessions."""
    order = np.random.default_rng([seed, 0x627564]).permutation(len(data.train_sessions))
    n = max(1, round(budget * len(order)))
    rows = np.flatnonzero(np.isin(data.train.index[:, 0], order[:n]))  # type: ignore[attr-defined]
    return rows, n


def _rows_of(y: np.ndarray) -> np.ndarray:
    """Targets (N, out) or (N, S, out) -> (M, out): every prediction is one row."""
    return y.reshape(-1, y.shape[-1])


def target_stats(data: ProbeData, rows: np.ndarray, tasks: Mapping[str, Task], slip_threshold: float,
                 device: torch.device) -> tuple[dict[str, tuple[Tensor, Tensor]], float]:
    """Standardization of the regression targets and the positive-class weight of slip, from the labels of the
    budget's training samples ``rows`` only (a budget limits every use of labels)."""
    stats, pos_weight = {}, 1.0
    for name, task in tasks.items():
        y = _rows_of(task.target(torch.from_numpy(data.train_labels[task.label][rows]), slip_threshold).numpy())
        if task.classes:
            continue
        if task.classify:
            pos = float(y.mean())
            pos_weight = float(np.clip((1.0 - pos) / max(pos, 1e-6), 1.0, 100.0))  # balance rare slip
        else:
            mean, std = y.mean(axis=0), np.maximum(y.std(axis=0), 1e-6)
            stats[name] = (torch.as_tensor(mean, device=device), torch.as_tensor(std, device=device))
    return stats, pos_weight


def baselines(data: ProbeData, tasks: Mapping[str, Task], slip_threshold: float) -> list[dict[str, Any]]:
    """What predicting the training mean (regression) or the majority class (slip) scores on the test split."""
    rows = []
    for name, task in tasks.items():
        tr = _rows_of(task.target(torch.from_numpy(data.train_labels[task.label]), slip_threshold).numpy())
        te = _rows_of(task.target(torch.from_numpy(window_labels(data.test, task.label)), slip_threshold).numpy())
        if task.classes:  # the most frequent training class
            majority = np.bincount(tr[:, 0].astype(np.int64), minlength=task.classes).argmax()
            guess = np.full(te.shape, float(majority), np.float32)
        else:
            guess = np.broadcast_to((tr.mean(axis=0) > 0.5).astype(np.float32) if task.classify
                                    else tr.mean(axis=0), te.shape)
        rows += [{"task": name, "metric": m, "value": v} for m, v in task.metrics(guess, te).items()]
    return rows
