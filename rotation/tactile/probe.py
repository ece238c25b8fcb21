"""Probe a pretrained touch encoder on labeled sessions: frozen features vs end-to-end training, at label budgets.

    rotate probe --checkpoint runs/pretrain --sessions data/touch --cache data/touch_cache --out runs/probe
    rotate probe --checkpoint d360_sparshx_img_mic_imu_pressure_base.pth --sessions data/real --tasks force slip
    rotate probe --encoder skin --checkpoint runs/pretrain_skin --sessions data/skin --out runs/probe_skin

For every variant and label budget, one attentive probe per task (rotation.tactile.pooling: a learned query
cross-attends over the encoder's layer-normed tokens, then an MLP head) is trained with Adam on the budget's
share of the training sessions and scored on held-out sessions (reference/sparsh.md "Probes"):

- ``pretrained``: the checkpoint's encoder, frozen (its tokens are computed once per batch for every task);
- ``e2e``: the same architecture from a random initialization (the checkpoint's input statistics), trained with
  each task's probe end to end, one encoder per task;
- ``image_only`` (Sparsh-X): the checkpoint's encoder reading only its image tokens, frozen (or
  ``--image-checkpoint``).

Sparsh-X tasks, from the labels simulated sessions store (rotation.data.session): ``force`` per-fingertip contact
force, along the camera axis and across it (N, sensor frame; RMSE of each); ``contact_force`` the same force split
at the strongest contact, normal and tangential (N; RMSE of each: many of this hand's contacts sit on the side of
the dome, where the camera axis is close to tangent to the contact); ``slip`` whether the fingertip slides
faster than ``slip_threshold`` (balanced accuracy); ``mass`` and ``friction`` of the object (RMSE; from
``labels/priv``).
Sparsh-skin tasks (``--encoder skin``, rotation.tactile.probe_skin): ``force`` per pad (instantaneous), ``pose``
and ``joystick`` (temporal: sequences of ``sequence_windows`` windows, a causal transformer block over the pooled
windows). Sessions are split into train and test by file; a budget b trains on the first max(1, round(b n)) of
the n training sessions in a seeded order (nested: 10% within 33% within 100%).

OUT: results.json ``{"rows": [{"task", "variant", "budget", "metric", "value"}, ...], ...}``, results.md (table),
probe.png (metric vs label budget per variant), <task>_over_time.png for temporal tasks (predicted vs true on a
test session, largest budget), config.json, tb/.
The report is rewritten after every (variant, budget) with ``"complete": false`` until the last one; Ctrl-C or
SIGTERM stop after the probe being trained and keep the finished rows.
"""

from __future__ import annotations

import copy
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
from rotation.data.dataset import check_fingers, check_session_sources, split_sessions
from rotation.data.session import SessionReader
from rotation.interrupt import StopSignals, ignore_stop_signals
from rotation.tactile.encoders import encoder_kind, kind_of, load_encoder
from rotation.tactile.loading import open_encoder_windows, session_paths, step_loader, to_device
from rotation.tactile.pooling import ProbeHead
from rotation.tactile.probe_data import (
    ProbeData,
    Task,
    baselines,
    budget_rows,
    open_probe_data,
    target_stats,
    window_labels,
)
from rotation.tactile.probe_report import write_report, write_traces
from rotation.tactile.probe_skin import (
    TemporalProbeHead,
    force_metrics,
    joystick_metrics,
    pose_metrics,
    relative_pose,
)
from rotation.tactile.runtime import (
    Processes,
    autocast,
    check_device,
    resolve_device,
    use_bf16,
)
from rotation.train.runs import summary_writer

VARIANTS = ("pretrained", "e2e", "image_only")
"""Sparsh-X's variants (Sparsh-skin has no image tokens: pretrained and e2e)."""
__all__ = ["TASKS", "SKIN_TASKS", "VARIANTS", "Config", "Task", "run", "window_labels"]


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
    "contact_force": Task("contact_force", 2, False, lambda y, _: y[:, :2],
                          lambda p, t: {"rmse_normal_N": _rmse(p[:, 0], t[:, 0]),
                                        "rmse_tangential_N": _rmse(p[:, 1], t[:, 1])}),
    "slip": Task("slip", 1, True, lambda y, thr: (y.reshape(-1, 1) > thr).float(),
                 lambda p, t: {"balanced_accuracy": balanced_accuracy(p[:, 0], t[:, 0])}),
    "mass": Task("priv", 1, False, lambda y, _: y[:, _MASS : _MASS + 1],
                 lambda p, t: {"rmse_kg": _rmse(p, t)}),
    "friction": Task("priv", 1, False, lambda y, _: y[:, _FRICTION : _FRICTION + 1],
                     lambda p, t: {"rmse": _rmse(p, t)}),
}
"""Sparsh-X task name -> definition (see the module docstring)."""
SKIN_TASKS: dict[str, Task] = {
    "force": Task("skin_force", 54, False, lambda y, _: y.reshape(y.shape[0], -1), force_metrics, loss="smooth_l1"),
    "pose": Task("object_pose", 6, False, lambda y, _: relative_pose(y), pose_metrics, temporal=True),
    "joystick": Task("joystick", 3, False, lambda y, _: y, joystick_metrics, temporal=True),
}
"""Sparsh-skin task name -> definition (rotation.tactile.probe_skin)."""
ENCODER_TASKS = {"sparshx": TASKS, "skin": SKIN_TASKS}
ENCODER_VARIANTS = {"sparshx": VARIANTS, "skin": ("pretrained", "e2e")}


@dataclass(frozen=True)
class Config:
    """Attentive probes of a touch encoder at label budgets (`rotate probe`)."""

    checkpoint: Path = Path("runs/pretrain")
    """Encoder: a `rotate pretrain` run directory, its encoder.safetensors, or a released Sparsh-X .pth."""
    encoder: str = "sparshx"
    """Encoder kind the checkpoint holds: sparshx (fingertip windows) or skin (whole-hand skin windows); it decides
    the tasks, variants and windows."""
    sessions: tuple[Path, ...] = (Path("touch_sessions"),)
    """Labeled session files or directories (simulated sessions carry force, slip and priv labels; skin sessions
    skin_force, object_pose, joystick)."""
    cache: Path | None = None
    """Pre-rendered window cache (rotate cache-touch; Sparsh-X only); None renders windows on the fly."""
    out: Path = Path("runs/probe")
    """Report directory: results.json, results.md, probe.png, config.json, tb/."""
    tasks: tuple[str, ...] | None = None
    """Tasks: Sparsh-X force, contact_force, slip, mass, friction; skin force, pose, joystick. None: every task of the
    encoder whose label all the sessions hold (skin cup sessions: force, pose; joystick sessions: force, joystick)."""
    variants: tuple[str, ...] | None = None
    """Variants among pretrained (frozen), e2e (trained end to end from scratch), image_only (Sparsh-X: frozen,
    image tokens). None: all of the encoder's."""
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
    """Use every stride-th frame as a window end (Sparsh-X: 30 fps image frames; skin: 100 Hz frames)."""
    sequence_windows: int = 10
    """Temporal skin tasks (pose, joystick): consecutive 0.1 s windows per sample (10 = 1 s of history)."""
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
        object.__setattr__(self, "sessions", check_session_sources(self.sessions))
        check_output_dir("out", self.out)
        if self.encoder not in ENCODER_TASKS:
            raise ValueError(f"encoder: unknown encoder {self.encoder!r}; encoders: {', '.join(ENCODER_TASKS)}")
        if self.cache is not None:
            check_output_dir("cache", self.cache)
            if self.encoder == "skin":
                raise ValueError("cache: the skin encoder reads its windows from the sessions (no cache); drop --cache")
        for name, allowed in (("tasks", tuple(ENCODER_TASKS[self.encoder])),
                              ("variants", ENCODER_VARIANTS[self.encoder])):
            values = getattr(self, name)
            if values is None:
                continue
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
                           ("head_hidden", 65536), ("sequence_windows", 1000)):
            check_int(name, getattr(self, name), 1, high)
        check_int("num_workers", self.num_workers, 0, 1024)
        if self.torch_threads is not None:
            check_int("torch_threads", self.torch_threads, 1, 4096)
        check_seed("seed", self.seed)
        check_number("lr", self.lr, 0.0, 1.0, low_open=True)
        check_number("slip_threshold", self.slip_threshold, 0.0, 10.0, low_open=True, unit="m/s")
        check_device(self.device, "device")

    @property
    def task_defs(self) -> dict[str, Task]:
        """The tasks of this run, by name, in the order given (default: all of the encoder's)."""
        tasks = ENCODER_TASKS[self.encoder]
        return {t: tasks[t] for t in (self.tasks if self.tasks is not None else tuple(tasks))}

    @property
    def variant_names(self) -> tuple[str, ...]:
        return self.variants if self.variants is not None else ENCODER_VARIANTS[self.encoder]


# ------------------------------------------------------------------------------------------------- models
class _Probes(nn.Module):
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

    def train(self, mode: bool = True) -> _Probes:
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
            with torch.no_grad():
                flat = interface.concat(self.encoder(inputs))  # (B [S], N, D)
            return {t: head(t, flat) for t in self.tasks}
        return {t: head(t, interface.concat(self.encoders[t](inputs))) for t in self.tasks}

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
    fresh = kind.rebuild(pretrained).to(device)
    theirs = dict(pretrained.named_buffers())
    with torch.no_grad():
        for name, buf in fresh.named_buffers():
            buf.copy_(theirs[name])
    return fresh


# ------------------------------------------------------------------------------------------------ training
def _targets(batch: dict[str, Tensor], task: Task, cfg: Config) -> Tensor:
    return task.target(batch[task.label].float(), cfg.slip_threshold)


def _train_probes(probes: _Probes, data: Dataset, tasks: dict[str, Task], cfg: Config,
                  stats: dict[str, tuple[Tensor, Tensor]], pos_weight: float, device: torch.device, bf16: bool,
                  bar: tqdm, writer: Any, tag: str) -> None:
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
        for name, task in tasks.items():
            y = _targets(batch, task, cfg)
            p = preds[name].float()
            if task.classify:
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
def _evaluate(probes: _Probes, data: Dataset, tasks: dict[str, Task], cfg: Config,
              stats: dict[str, tuple[Tensor, Tensor]], device: torch.device, bf16: bool
              ) -> tuple[dict[str, dict[str, float]], dict[str, dict[str, np.ndarray]]]:
    """Metrics per task on ``data``, and for temporal tasks the traces of the last window of every sequence
    (``pred``, ``true`` (N, outputs), ``time`` (N,) s, ``session`` (N,)) for the plots over time."""
    probes.eval()
    loader = DataLoader(data, batch_size=cfg.batch_size, shuffle=False, num_workers=cfg.num_workers,
                        worker_init_fn=ignore_stop_signals)
    preds: dict[str, list[np.ndarray]] = {t: [] for t in tasks}
    targets: dict[str, list[np.ndarray]] = {t: [] for t in tasks}
    times, sessions = [], []
    for batch in loader:
        batch = to_device(batch, device)
        with autocast(device, bf16):
            out = probes(probes.reference.preprocess(batch))
        for name, task in tasks.items():
            p = out[name].float()
            if task.classify:
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
        if task.temporal:  # (N, S, out): the last window of each sequence has the whole history
            traces[name] = {"pred": p[:, -1], "true": t[:, -1], "time": np.concatenate(times)[:, -1],
                            "session": np.concatenate(sessions)}
    return scores, traces


def _available_tasks(cfg: Config, paths: list[Path]) -> dict[str, Task]:
    """The tasks of a run: those asked for, or (``tasks`` None) every task of the encoder whose label every session
    holds (skin cup sessions: force and pose; joystick sessions: force and joystick)."""
    if cfg.tasks is not None:
        return cfg.task_defs
    have: set[str] | None = None
    for path in paths:
        with SessionReader(path) as r:
            names = {n.split("/", 1)[1] for n in r.names if n.startswith("labels/")}
        have = names if have is None else have & names
    tasks = {n: t for n, t in cfg.task_defs.items() if t.label in (have or set())}
    if not tasks:
        raise ValueError(f"probe: no {cfg.encoder} task has its labels in every session of "
                         f"{', '.join(map(str, cfg.sessions))} (labels in all of them: {sorted(have or ())}; tasks: "
                         + ", ".join(f"{n} <- labels/{t.label}" for n, t in cfg.task_defs.items()) + ")")
    return tasks


def _prepare(cfg: Config) -> tuple[dict[str, Task], dict[bool, ProbeData]]:
    """The run's tasks, and samples for each kind of task: {False: single windows, True: sequences} (those needed)."""
    paths = session_paths(cfg.sessions)
    if len(paths) < 2:
        raise ValueError(f"probe: need at least 2 session files to split into train and test, found {len(paths)} "
                         f"in {', '.join(map(str, cfg.sessions))}")
    all_tasks = _available_tasks(cfg, paths)
    train_paths, test_paths = split_sessions(paths, cfg.test_fraction, cfg.seed)
    groups: dict[bool, ProbeData] = {}
    for temporal in (False, True):
        tasks = {n: t for n, t in all_tasks.items() if t.temporal == temporal}
        if not tasks:
            continue
        labels = tuple(sorted({t.label for t in tasks.values()}))
        if cfg.cache is not None:
            open_encoder_windows(cfg.encoder, paths, cfg.cache, cfg.fingers, cfg.stride, labels=labels,
                                 progress=cfg.progress, workers=cfg.num_workers)
        groups[temporal] = open_probe_data(cfg.encoder, train_paths, test_paths, cfg.cache, cfg.fingers, cfg.stride,
                                           labels, cfg.sequence_windows if temporal else None)
    return all_tasks, groups


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
    if kind_of(pretrained) != cfg.encoder:
        raise ValueError(f"encoder: {cfg.checkpoint} holds a {kind_of(pretrained)} encoder, not {cfg.encoder}; pass "
                         f"--encoder {kind_of(pretrained)}")
    all_tasks, groups = _prepare(cfg)
    out = Path(cfg.out)
    save_config(cfg, out / "config.json")
    writer = summary_writer(out / "tb", 0)
    rows: list[dict[str, Any]] = []
    variants = cfg.variant_names
    runs = len(variants) * len(cfg.budgets) * len(groups)
    bar = tqdm(total=runs * cfg.steps, unit="step", desc="probe", disable=not cfg.progress, dynamic_ncols=True)
    sessions_used: dict[str, int] = {}
    traces: dict[str, dict[str, dict[str, np.ndarray]]] = {}  # task -> variant -> trace (largest budget)
    first = next(iter(groups.values()))
    fixed = {"baselines": [b for temporal, data in groups.items() for b in baselines(
                 data, {n: t for n, t in all_tasks.items() if t.temporal == temporal}, cfg.slip_threshold)],
             "encoder": encoder_kind(kind_of(pretrained)).describe(pretrained), "checkpoint": str(cfg.checkpoint),
             "train_sessions": len(first.train_sessions), "test_sessions": len(first.test_sessions),
             "train_windows": len(first.train), "test_windows": len(first.test), "config": to_jsonable(cfg)}

    def report(complete: bool) -> dict[str, Any]:
        """The report so far, written after every (variant, budget): a stopped run keeps what it finished."""
        out_report = {"rows": rows, "complete": complete, **fixed, "sessions_per_budget": sessions_used}
        if traces:
            out_report["trace_plots"] = write_traces(traces, out, budget=max(cfg.budgets))
        write_report(out_report, out)
        return out_report

    try:
        with StopSignals() as stop:
            for variant in variants:
                encoder = _variant_encoder(variant, pretrained, cfg, device)
                for budget in sorted(cfg.budgets):
                    for temporal, data in groups.items():
                        tasks = {n: t for n, t in all_tasks.items() if t.temporal == temporal}
                        rows_b, n_sessions = budget_rows(data, budget, cfg.seed)
                        sessions_used[str(budget)] = n_sessions
                        stats, pos_weight = target_stats(data, rows_b, tasks, cfg.slip_threshold, device)
                        torch.manual_seed(cfg.seed)
                        probes = _Probes(encoder, variant != "e2e", tasks, cfg).to(device)
                        bar.set_postfix(variant=variant, budget=budget)
                        _train_probes(probes, Subset(data.train, rows_b.tolist()), tasks, cfg, stats, pos_weight,
                                      device, bf16, bar, writer, f"{variant}/budget_{budget}")
                        scores, task_traces = _evaluate(probes, data.test, tasks, cfg, stats, device, bf16)
                        for task, metrics in scores.items():
                            rows += [{"task": task, "variant": variant, "budget": float(budget), "metric": m,
                                      "value": v} for m, v in metrics.items()]
                        if budget == max(cfg.budgets):
                            for task, trace in task_traces.items():
                                traces.setdefault(task, {})[variant] = trace
                        del probes
                    report(complete=False)
                    stop.raise_if_requested(f"probe: stopped after {variant} at budget {budget:g}; the finished "
                                            f"rows are in {out / 'results.md'}")
    finally:
        bar.close()
        writer.close()
    final = report(complete=True)
    print(f"probe: {len(rows)} results for {len(variants)} variant(s) x {len(cfg.budgets)} budget(s) -> "
          f"{out / 'results.md'}")
    return final
