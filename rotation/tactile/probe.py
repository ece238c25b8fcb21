"""Probe a pretrained touch encoder on labeled sessions: frozen features vs end-to-end training, at label budgets.

    rotate probe --checkpoint runs/pretrain --sessions data/touch --cache data/touch_cache --out runs/probe
    rotate probe --checkpoint d360_sparshx_img_mic_imu_pressure_base.pth --sessions data/real --tasks force slip

For every variant and label budget, one attentive probe per task (rotation.tactile.pooling: a learned query
cross-attends over the encoder's layer-normed tokens, then an MLP head) is trained with Adam on the budget's
share of the training sessions and scored on held-out sessions (reference/sparsh.md "Probes"):

- ``pretrained``: the checkpoint's encoder, frozen (its tokens are computed once per batch for every task);
- ``e2e``: the same architecture from a random initialization (the checkpoint's input statistics), trained with
  each task's probe end to end, one encoder per task;
- ``image_only``: the checkpoint's encoder reading only its image tokens, frozen (or ``--image-checkpoint``).

Tasks, from the labels simulated sessions store (rotation.data.session): ``force`` per-fingertip contact force,
normal and shear (N, sensor frame; RMSE of each); ``slip`` whether the fingertip slides faster than
``slip_threshold`` (balanced accuracy); ``mass`` and ``friction`` of the object (RMSE; from ``labels/priv``).
Sessions are split into train and test by file; a budget b trains on the first max(1, round(b n)) of the n
training sessions in a seeded order (nested: 10% within 33% within 100%).

OUT: results.json ``{"rows": [{"task", "variant", "budget", "metric", "value"}, ...], ...}``, results.md (table),
probe.png (metric vs label budget per variant), config.json, tb/.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset, Subset
from tqdm import tqdm

from envs.constants import FINGERS, PRIV_FIELDS
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import save_config, to_jsonable
from rotation.data.dataset import split_sessions
from rotation.data.session import SessionReader
from rotation.data.window_cache import CachedWindows
from rotation.tactile.encoders import encoder_kind, kind_of, load_encoder
from rotation.tactile.loading import check_fingers, open_windows, session_paths, step_loader, to_device
from rotation.tactile.pooling import ProbeHead
from rotation.tactile.probe_report import write_report
from rotation.tactile.runtime import (
    Processes,
    autocast,
    check_device,
    resolve_device,
    summary_writer,
    use_bf16,
)

VARIANTS = ("pretrained", "e2e", "image_only")
_TIME_EPS = 1e-6


@dataclass(frozen=True)
class Task:
    """One probe task: which label, how many outputs, its loss and its metrics."""

    label: str
    """Dataset label the target comes from."""
    outputs: int
    classify: bool
    """Binary classification (BCE, balanced accuracy) instead of regression (MSE on standardized targets)."""
    target: Callable[[Tensor, float], Tensor]
    """(label batch, slip threshold) -> (B, outputs) float targets."""
    metrics: Callable[[np.ndarray, np.ndarray], dict[str, float]]
    """(predictions, targets) (N, outputs), in physical units / {0, 1} -> {metric: value}."""


def _rmse(pred: np.ndarray, target: np.ndarray) -> float:
    return float(np.sqrt(np.mean((pred - target) ** 2)))


def balanced_accuracy(pred: np.ndarray, target: np.ndarray) -> float:
    """Mean of the recall of each class present in ``target`` (0/1 arrays)."""
    recalls = [float(np.mean(pred[target == c] == c)) for c in (0, 1) if np.any(target == c)]
    return float(np.mean(recalls)) if recalls else float("nan")


_MASS, _FRICTION = PRIV_FIELDS.index("mass"), PRIV_FIELDS.index("friction")
TASKS: dict[str, Task] = {
    "force": Task("force", 3, False, lambda y, _: y[:, :3],
                  lambda p, t: {"rmse_normal_N": _rmse(p[:, 0], t[:, 0]), "rmse_shear_N": _rmse(p[:, 1:], t[:, 1:])}),
    "slip": Task("slip", 1, True, lambda y, thr: (y.reshape(-1, 1) > thr).float(),
                 lambda p, t: {"balanced_accuracy": balanced_accuracy(p[:, 0], t[:, 0])}),
    "mass": Task("priv", 1, False, lambda y, _: y[:, _MASS : _MASS + 1],
                 lambda p, t: {"rmse_kg": _rmse(p, t)}),
    "friction": Task("priv", 1, False, lambda y, _: y[:, _FRICTION : _FRICTION + 1],
                     lambda p, t: {"rmse": _rmse(p, t)}),
}
"""Task name -> definition (see the module docstring)."""


@dataclass(frozen=True)
class Config:
    """Attentive probes of a touch encoder at label budgets (`rotate probe`)."""

    checkpoint: Path = Path("runs/pretrain")
    """Encoder: a `rotate pretrain` run directory, its encoder.safetensors, or a released Sparsh-X .pth."""
    sessions: tuple[Path, ...] = (Path("touch_sessions"),)
    """Labeled session files or directories (simulated sessions carry force, slip and priv labels)."""
    cache: Path | None = None
    """Pre-rendered window cache (rotate cache-touch); None renders windows on the fly."""
    out: Path = Path("runs/probe")
    """Report directory: results.json, results.md, probe.png, config.json, tb/."""
    tasks: tuple[str, ...] = tuple(TASKS)
    """Tasks among force, slip, mass, friction."""
    variants: tuple[str, ...] = VARIANTS
    """Variants among pretrained (frozen), e2e (trained end to end from scratch), image_only (frozen, image tokens)."""
    budgets: tuple[float, ...] = (0.1, 0.33, 1.0)
    """Label budgets: fractions of the training sessions, each in (0, 1]."""
    image_checkpoint: Path | None = None
    """Encoder of the image_only variant (e.g. a released image-only Sparsh-X); None: the checkpoint's encoder
    restricted to its image tokens."""
    test_fraction: float = 0.2
    """Fraction of the session files held out for testing (split by file, seeded)."""
    fingers: tuple[str, ...] = FINGERS
    """Fingertips whose windows are used."""
    stride: int = 5
    """Use every stride-th image frame as a window end."""
    steps: int = 2000
    """Optimizer steps per probe (the same for every budget)."""
    batch_size: int = 32
    """Windows per step."""
    lr: float = 1e-4
    """Adam learning rate of the probes (and of the end-to-end encoders)."""
    pooler_heads: int = 4
    """Attention heads of the attentive pooler (the encoder width must be divisible by it)."""
    head_hidden: int = 256
    """Hidden width of each task's MLP head."""
    slip_threshold: float = 0.005
    """Slip speed (m/s) above which a fingertip counts as slipping."""
    num_workers: int = 4
    """DataLoader worker processes."""
    device: str = "auto"
    """torch device: auto, cpu, cuda, cuda:1, ..."""
    precision: Literal["auto", "bf16", "fp32"] = "auto"
    """auto (bfloat16 autocast on a GPU), bf16 or fp32."""
    seed: int = 0
    """Seed of the split, the budgets, the probes' initialization and batch order."""
    torch_threads: int | None = None
    """torch CPU threads (None = torch's default)."""
    progress: bool = True
    """Show a progress bar."""

    def __post_init__(self) -> None:
        check_types(self)
        if not self.sessions:
            raise ValueError("sessions: give at least one session file or directory")
        object.__setattr__(self, "sessions", tuple(Path(p) for p in self.sessions))  # JSON gives strings back
        check_output_dir("out", self.out)
        if self.cache is not None:
            check_output_dir("cache", self.cache)
        for name, allowed in (("tasks", tuple(TASKS)), ("variants", VARIANTS)):
            values = getattr(self, name)
            bad = [v for v in values if v not in allowed]
            if bad or not values or len(set(values)) != len(values):
                raise ValueError(f"{name}: need distinct names among {', '.join(allowed)}, got {list(values)}")
        if not self.budgets or len(set(self.budgets)) != len(self.budgets):
            raise ValueError(f"budgets: need distinct fractions in (0, 1], got {list(self.budgets)}")
        for b in self.budgets:
            check_number("budgets", b, 0.0, 1.0, low_open=True)
        check_number("test_fraction", self.test_fraction, 0.0, 1.0, low_open=True, high_open=True)
        check_fingers(self.fingers)
        for name, high in (("stride", 1000), ("steps", 10**9), ("batch_size", 65536), ("pooler_heads", 256),
                           ("head_hidden", 65536)):
            check_int(name, getattr(self, name), 1, high)
        check_int("num_workers", self.num_workers, 0, 1024)
        if self.torch_threads is not None:
            check_int("torch_threads", self.torch_threads, 1, 4096)
        check_seed("seed", self.seed)
        check_number("lr", self.lr, 0.0, 1.0, low_open=True)
        check_number("slip_threshold", self.slip_threshold, 0.0, 10.0, low_open=True, unit="m/s")
        check_device(self.device, "device")


# ------------------------------------------------------------------------------------------------- labels
def window_labels(ds: Dataset, name: str) -> np.ndarray:
    """Label ``name`` of every window of a TouchWindows or CachedWindows, read without rendering (N, ...)."""
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
        if name in ("force", "slip", "contact"):  # per fingertip
            value = value[np.arange(len(rows)), ds.index[rows, 1]]  # type: ignore[attr-defined]
        out.append(value.astype(np.float32))
    return np.concatenate(out)


# ------------------------------------------------------------------------------------------------- models
class _Probes(nn.Module):
    """One probe head per task over a frozen shared encoder, or each over its own trained encoder (e2e)."""

    def __init__(self, encoder: nn.Module, frozen: bool, tasks: tuple[str, ...], cfg: Config):
        super().__init__()
        self.frozen, self.tasks = frozen, tasks
        width = encoder.token_interface.width
        self.heads = nn.ModuleDict({t: ProbeHead(width, TASKS[t].outputs, cfg.pooler_heads, cfg.head_hidden)
                                    for t in tasks})
        if frozen:
            self.encoder = encoder.eval().requires_grad_(False)
        else:
            self.encoders = nn.ModuleDict({t: copy.deepcopy(encoder).train() for t in tasks})
        self.__dict__["reference"] = encoder  # preprocess and token interface (not a submodule: no training)

    def train(self, mode: bool = True) -> _Probes:
        super().train(mode)
        if self.frozen:
            self.encoder.eval()  # a frozen encoder stays in eval mode (no drop path)
        return self

    def forward(self, inputs: dict[str, Tensor]) -> dict[str, Tensor]:
        interface = self.reference.token_interface
        if self.frozen:
            with torch.no_grad():
                flat = interface.concat(self.encoder(inputs))  # (B, N, D)
            return {t: self.heads[t](flat) for t in self.tasks}
        return {t: self.heads[t](interface.concat(self.encoders[t](inputs))) for t in self.tasks}

    def trainable(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]


def _variant_encoder(variant: str, pretrained: nn.Module, cfg: Config, device: torch.device) -> nn.Module:
    kind = encoder_kind(kind_of(pretrained))
    if variant == "pretrained":
        return pretrained
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
    c = pretrained.cfg  # type: ignore[attr-defined]
    fresh = kind.build(c.size, tuple(c.modalities), c.fusion, c.drop_path).to(device)
    theirs = dict(pretrained.named_buffers())
    with torch.no_grad():
        for name, buf in fresh.named_buffers():
            buf.copy_(theirs[name])
    return fresh


# ------------------------------------------------------------------------------------------------ training
@dataclass
class _Data:
    train: Dataset
    test: Dataset
    train_sessions: list[Path]
    test_sessions: list[Path]
    train_labels: dict[str, np.ndarray]
    """Label name -> (N_train, ...) labels of every training window (read without rendering)."""


def _targets(batch: dict[str, Tensor], task: str, cfg: Config) -> Tensor:
    return TASKS[task].target(batch[TASKS[task].label].float(), cfg.slip_threshold)


def _train_probes(probes: _Probes, data: Dataset, cfg: Config, stats: dict[str, tuple[Tensor, Tensor]],
                  pos_weight: float, device: torch.device, bf16: bool, bar: tqdm, writer: Any, tag: str) -> None:
    opt = torch.optim.Adam(probes.trainable(), lr=cfg.lr)
    loader = step_loader(data, cfg.batch_size, Processes(), cfg.seed, 0, cfg.steps, cfg.num_workers,
                         device.type == "cuda")
    probes.train()
    pw = torch.tensor([pos_weight], device=device)
    for step, batch in enumerate(loader):
        batch = to_device(batch, device)
        inputs = probes.reference.preprocess(batch)
        with autocast(device, bf16):
            preds = probes(inputs)
        losses = {}
        for t in probes.tasks:
            y = _targets(batch, t, cfg)
            p = preds[t].float()
            if TASKS[t].classify:
                losses[t] = F.binary_cross_entropy_with_logits(p, y, pos_weight=pw)
            else:
                mean, std = stats[t]
                losses[t] = F.mse_loss(p, (y - mean) / std)
        loss = torch.stack(list(losses.values())).sum()  # independent parameters: each probe sees its own gradient
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        bar.update(1)
        if writer is not None and (step % 50 == 0 or step + 1 == cfg.steps):
            for t, v in losses.items():
                writer.add_scalar(f"{tag}/{t}_loss", float(v.detach()), global_step=step)


@torch.no_grad()
def _evaluate(probes: _Probes, data: Dataset, cfg: Config, stats: dict[str, tuple[Tensor, Tensor]],
              device: torch.device, bf16: bool) -> dict[str, dict[str, float]]:
    probes.eval()
    loader = DataLoader(data, batch_size=cfg.batch_size, shuffle=False, num_workers=cfg.num_workers)
    preds: dict[str, list[np.ndarray]] = {t: [] for t in probes.tasks}
    targets: dict[str, list[np.ndarray]] = {t: [] for t in probes.tasks}
    for batch in loader:
        batch = to_device(batch, device)
        with autocast(device, bf16):
            out = probes(probes.reference.preprocess(batch))
        for t in probes.tasks:
            p = out[t].float()
            if TASKS[t].classify:
                p = (p > 0).float()
            else:
                mean, std = stats[t]
                p = p * std + mean
            preds[t].append(p.cpu().numpy())
            targets[t].append(_targets(batch, t, cfg).cpu().numpy())
    return {t: TASKS[t].metrics(np.concatenate(preds[t]), np.concatenate(targets[t])) for t in probes.tasks}


def _prepare(cfg: Config, device: torch.device) -> _Data:
    paths = session_paths(cfg.sessions)
    if len(paths) < 2:
        raise ValueError(f"probe: need at least 2 session files to split into train and test, found {len(paths)} "
                         f"in {', '.join(map(str, cfg.sessions))}")
    labels = tuple(sorted({TASKS[t].label for t in cfg.tasks}))
    train_paths, test_paths = split_sessions(paths, cfg.test_fraction, cfg.seed)
    if cfg.cache is not None:
        open_windows(paths, cfg.cache, cfg.fingers, cfg.stride, labels=labels, progress=cfg.progress,
                     workers=cfg.num_workers)
    train = open_windows(train_paths, cfg.cache, cfg.fingers, cfg.stride, labels=labels, build=False)
    test = open_windows(test_paths, cfg.cache, cfg.fingers, cfg.stride, labels=labels, build=False)
    if len(test) == 0 or len(train) == 0:
        raise ValueError(f"probe: no windows in the {'test' if len(test) == 0 else 'training'} sessions (each needs "
                         "at least 1.12 s of touch)")
    return _Data(train, test, train_paths, test_paths, {name: window_labels(train, name) for name in labels})


def _target_stats(data: _Data, rows: np.ndarray, cfg: Config, device: torch.device
                  ) -> tuple[dict[str, tuple[Tensor, Tensor]], float]:
    """Standardization of the regression targets and the positive-class weight of slip, from the labels of the
    budget's training windows ``rows`` only (a budget limits every use of labels)."""
    stats, pos_weight = {}, 1.0
    for t in cfg.tasks:
        y = TASKS[t].target(torch.from_numpy(data.train_labels[TASKS[t].label][rows]), cfg.slip_threshold).numpy()
        if TASKS[t].classify:
            pos = float(y.mean())
            pos_weight = float(np.clip((1.0 - pos) / max(pos, 1e-6), 1.0, 100.0))  # balance rare slip
        else:
            mean, std = y.mean(axis=0), np.maximum(y.std(axis=0), 1e-6)
            stats[t] = (torch.as_tensor(mean, device=device), torch.as_tensor(std, device=device))
    return stats, pos_weight


def _budget_rows(data: _Data, budget: float, seed: int) -> tuple[np.ndarray, int]:
    """Training windows of the first max(1, round(budget n)) training sessions in a seeded order (nested budgets),
    and that number of sessions."""
    order = np.random.default_rng([seed, 0x627564]).permutation(len(data.train_sessions))
    n = max(1, round(budget * len(order)))
    rows = np.flatnonzero(np.isin(data.train.index[:, 0], order[:n]))  # type: ignore[attr-defined]
    return rows, n


def _baselines(data: _Data, cfg: Config) -> list[dict[str, Any]]:
    """What predicting the training mean (regression) or the majority class (slip) scores on the test split."""
    rows = []
    for t in cfg.tasks:
        task = TASKS[t]
        tr = task.target(torch.from_numpy(data.train_labels[task.label]), cfg.slip_threshold).numpy()
        te = task.target(torch.from_numpy(window_labels(data.test, task.label)), cfg.slip_threshold).numpy()
        guess = np.broadcast_to((tr.mean(axis=0) > 0.5).astype(np.float32) if task.classify else tr.mean(axis=0),
                                te.shape)
        rows += [{"task": t, "metric": m, "value": v} for m, v in task.metrics(guess, te).items()]
    return rows


def run(cfg: Config) -> dict[str, Any]:
    """Train and score every (variant, budget, task) probe; writes the report and returns it."""
    threads = torch.get_num_threads()
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    try:
        return _run(cfg)
    finally:
        torch.set_num_threads(threads)


def _run(cfg: Config) -> dict[str, Any]:
    device = resolve_device(cfg.device)
    bf16 = use_bf16(cfg.precision, device)
    pretrained = load_encoder(cfg.checkpoint, device=device)
    data = _prepare(cfg, device)
    out = Path(cfg.out)
    save_config(cfg, out / "config.json")
    writer = summary_writer(out / "tb", 0)
    rows: list[dict[str, Any]] = []
    runs = len(cfg.variants) * len(cfg.budgets)
    bar = tqdm(total=runs * cfg.steps, unit="step", desc="probe", disable=not cfg.progress, dynamic_ncols=True)
    sessions_used: dict[str, int] = {}
    try:
        for variant in cfg.variants:
            encoder = _variant_encoder(variant, pretrained, cfg, device)
            for budget in sorted(cfg.budgets):
                rows_b, n_sessions = _budget_rows(data, budget, cfg.seed)
                sessions_used[str(budget)] = n_sessions
                stats, pos_weight = _target_stats(data, rows_b, cfg, device)
                torch.manual_seed(cfg.seed)
                probes = _Probes(encoder, variant != "e2e", cfg.tasks, cfg).to(device)
                bar.set_postfix(variant=variant, budget=budget)
                _train_probes(probes, Subset(data.train, rows_b.tolist()), cfg, stats, pos_weight, device, bf16, bar,
                              writer, f"{variant}/budget_{budget}")
                scores = _evaluate(probes, data.test, cfg, stats, device, bf16)
                for task, metrics in scores.items():
                    rows += [{"task": task, "variant": variant, "budget": float(budget), "metric": m, "value": v}
                             for m, v in metrics.items()]
                del probes
    finally:
        bar.close()
        writer.close()
    report = {"rows": rows, "baselines": _baselines(data, cfg),
              "encoder": encoder_kind(kind_of(pretrained)).describe(pretrained), "checkpoint": str(cfg.checkpoint),
              "train_sessions": len(data.train_sessions), "test_sessions": len(data.test_sessions),
              "train_windows": len(data.train), "test_windows": len(data.test),
              "sessions_per_budget": sessions_used, "config": to_jsonable(cfg)}
    write_report(report, out)
    print(f"probe: {len(rows)} results for {len(cfg.variants)} variant(s) x {len(cfg.budgets)} budget(s) -> "
          f"{out / 'results.md'}")
    return report
