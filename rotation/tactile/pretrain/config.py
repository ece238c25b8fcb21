"""The config of `rotate pretrain` (one dataclass for both encoders) and what may change when a run is resumed."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from envs.constants import FINGERS
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import from_jsonable
from rotation.data.dataset import check_fingers, check_session_sources
from rotation.tactile.models.encoders import ENCODERS, encoder_kind, parse_groups
from rotation.tactile.pretrain.objectives import SkinObjectiveConfig
from rotation.tactile.runtime import check_device
from rotation.tactile.ssl import MaskConfig

HEAD_SIZES = {"tinier": (256, 1024), "tiny": (1024, 8192), "small": (2048, 16384), "base": (2048, 65536)}
"""Encoder size -> (head hidden width, prototypes) when not given: DINO's 2048 / 65,536 for base
(docs/reference/sparsh.md), smaller for the small models so the head does not dwarf the encoder."""


@dataclass(frozen=True)
class Config:
    """Self-supervised pretraining of a touch encoder (`rotate pretrain`)."""

    sessions: tuple[Path, ...] = (Path("touch_sessions"),)
    """Session files or directories (every *.h5 below them), simulated or recorded."""
    cache: Path | None = None
    """Pre-rendered window cache (rotate cache-touch); sessions missing from it are rendered into it first. None:
    render windows on the fly (slow: use for small runs)."""
    out: Path = Path("runs/pretrain")
    """Run directory: config.json, checkpoints, encoder.safetensors, tb/."""
    encoder: str = "sparshx"
    """Encoder to pretrain: sparshx (Digit 360 fingertips) or skin (Sparsh-skin, the Xela skin of the hand)."""
    size: str = "tiny"
    """Encoder size: tinier, tiny, small or base."""
    modalities: str = ""
    """Sparsh-X token groups (modalities), comma-separated; empty = all of the encoder's (skin has one)."""
    fusion: str = "bottleneck"
    """Sparsh-X fusion layers: bottleneck or vanilla."""
    unimodal_layers: int | None = None
    """Sparsh-X unimodal layers per modality instead of the size's (tinier: 6); fewer make a faster encoder (4
    fingertips on 2 CPU cores: tinier 61 ms, 4 + 2 layers 46 ms, 3 + 1 layers 31 ms)."""
    fusion_layers: int | None = None
    """Sparsh-X fusion layers instead of the size's (tinier: 2; 0 = none: the modalities stay independent)."""
    drop_path: float = 0.1
    """Stochastic depth of the student's last layer (Sparsh-X: 0.1; 0 = none)."""
    fingers: tuple[str, ...] = FINGERS
    """Fingertips whose windows are used (Sparsh-X)."""
    stride: int = 5
    """Use every stride-th frame as a window end: Sparsh-X image frames (30 fps / 5 = 6 windows per second and
    fingertip), skin frames (100 Hz / 5 = 20 windows per second)."""
    steps: int = 20_000
    """Optimizer steps."""
    batch_size: int = 64
    """Windows per step and process (the global batch is batch_size x processes)."""
    lr: float = 1e-4
    """Peak learning rate (Sparsh-X: 1e-4)."""
    lr_start: float = 1e-5
    """Learning rate at step 0, warmed up linearly to lr."""
    lr_end: float = 1e-6
    """Learning rate at the last step (cosine from lr)."""
    warmup_fraction: float = 0.15
    """Fraction of the steps spent warming the learning rate up (Sparsh-X: 30 of 200 epochs)."""
    weight_decay: float = 0.05
    """AdamW weight decay at step 0 (parameters with >= 2 dims only)."""
    weight_decay_end: float = 0.05
    """Weight decay at the last step (cosine; equal to weight_decay = constant)."""
    clip_grad: float | None = 10.0
    """Clip the gradients' global norm to this (Sparsh-X: 10); None = no clipping."""
    ema_start: float = 0.994
    """Teacher EMA momentum at step 0, cosine ramp to ema_end."""
    ema_end: float = 1.0
    """Teacher EMA momentum at the last step."""
    student_temp: float = 0.1
    """Temperature of the student's softmax."""
    teacher_temp_start: float = 0.04
    """Teacher temperature at step 0."""
    teacher_temp: float = 0.07
    """Teacher temperature after its warm-up."""
    teacher_temp_warmup_fraction: float = 0.05
    """Fraction of the steps over which the teacher temperature warms up (Sparsh-X: 10 of 200 epochs)."""
    center_momentum: float = 0.9
    """EMA momentum of the per-set centers."""
    head_hidden: int | None = None
    """Hidden width of the projection head (None = by size: 256 tinier, 1024 tiny, 2048 small and base)."""
    head_bottleneck: int = 256
    """Bottleneck width of the projection head (L2-normalized)."""
    prototypes: int | None = None
    """Prototypes K (None = by size: 1024 tinier, 8192 tiny, 16384 small, 65536 base)."""
    mask: MaskConfig = field(default_factory=MaskConfig)
    """Sparsh-X views: block scales, local views, fewest kept tokens."""
    skin: SkinObjectiveConfig = field(default_factory=SkinObjectiveConfig)
    """Sparsh-skin views (global / local blocks over the taxel order, iBOT masks) and loss weights."""
    stats_windows: int = 2048
    """Windows (a seeded random subset) from which the encoder's input normalization (audio per mel bin, pressure,
    image) is fitted before the first step."""
    num_workers: int = 4
    """DataLoader worker processes per training process."""
    device: str = "auto"
    """torch device: auto (this process's GPU if there is one), cpu, cuda, cuda:1, ..."""
    precision: Literal["auto", "bf16", "fp32"] = "auto"
    """auto (bfloat16 autocast on a GPU, float32 on the CPU), bf16 or fp32."""
    checkpoint_every: int = 1000
    """Steps between checkpoints (and exports of encoder.safetensors)."""
    keep_checkpoints: int = 3
    """Newest checkpoints kept."""
    log_every: int = 20
    """Steps between TensorBoard points."""
    seed: int = 0
    """Seed of the initialization, batch order, masks and drop path."""
    resume: bool = False
    """Continue from the newest checkpoint in out (the saved config must match, except run-time options)."""
    progress: bool = True
    """Show a progress bar."""
    torch_threads: int | None = None
    """torch CPU threads per process (None = torch's default; with several processes, the cores divided among
    them)."""
    nproc_per_node: int = 1
    """Training processes on this machine (> 1: relaunch through torchrun with DistributedDataParallel)."""
    nnodes: int = 1
    """Machines of a multi-node run (torchrun --nnodes)."""
    node_rank: int = 0
    """This machine's rank in a multi-node run (torchrun --node-rank)."""
    master_addr: str = ""
    """Address of the rank-0 machine of a multi-node run (torchrun --master-addr); empty on one machine."""
    master_port: int = 29500
    """Port of the rank-0 machine (torchrun --master-port)."""

    def __post_init__(self) -> None:
        check_types(self)
        object.__setattr__(self, "sessions", check_session_sources(self.sessions))
        check_output_dir("out", self.out)
        if self.cache is not None:
            check_output_dir("cache", self.cache)
            if self.encoder == "skin":
                raise ValueError("cache: the skin encoder reads its windows from the sessions (no cache); drop --cache")
        if self.encoder not in ENCODERS:
            raise ValueError(f"encoder: unknown encoder {self.encoder!r}; encoders: {', '.join(ENCODERS)}")
        kind = encoder_kind(self.encoder)
        if self.size not in kind.sizes:
            raise ValueError(f"size: unknown size {self.size!r}; sizes: {', '.join(kind.sizes)}")
        parse_groups(self.modalities, self.encoder)
        if self.fusion not in ("bottleneck", "vanilla"):
            raise ValueError(f"fusion: must be bottleneck or vanilla, got {self.fusion!r}")
        for name in ("unimodal_layers", "fusion_layers"):
            if getattr(self, name) is not None:
                check_int(name, getattr(self, name), 0, 64)
                if self.encoder != "sparshx":
                    raise ValueError(f"{name}: a Sparsh-X option; the skin encoder's layers come with its size")
        if self.unimodal_layers == 0 and self.fusion_layers == 0:
            raise ValueError("unimodal_layers, fusion_layers: the encoder needs at least one layer")
        check_fingers(self.fingers)
        check_number("drop_path", self.drop_path, 0.0, 1.0, high_open=True)
        for name, high in (("stride", 1000), ("steps", 10**9), ("batch_size", 65536), ("checkpoint_every", 10**9),
                           ("keep_checkpoints", 1000), ("log_every", 10**9), ("head_bottleneck", 65536),
                           ("stats_windows", 10**7), ("nproc_per_node", 1024), ("nnodes", 100_000)):
            check_int(name, getattr(self, name), 1, high)
        for name, high in (("head_hidden", 65536), ("prototypes", 2**20), ("torch_threads", 4096)):
            if getattr(self, name) is not None:
                check_int(name, getattr(self, name), 1, high)
        check_int("num_workers", self.num_workers, 0, 1024)
        check_int("node_rank", self.node_rank, 0, self.nnodes - 1)
        check_seed("seed", self.seed)
        for name in ("lr", "lr_start", "lr_end"):
            check_number(name, getattr(self, name), 0.0, 1.0, low_open=True)
        for name in ("student_temp", "teacher_temp_start", "teacher_temp"):
            check_number(name, getattr(self, name), 0.0, 10.0, low_open=True)
        for name in ("weight_decay", "weight_decay_end"):
            check_number(name, getattr(self, name), 0.0, 10.0)
        if self.clip_grad is not None:
            check_number("clip_grad", self.clip_grad, 0.0, 1e6, low_open=True)
        for name in ("warmup_fraction", "teacher_temp_warmup_fraction"):
            check_number(name, getattr(self, name), 0.0, 1.0, high_open=True)
        for name in ("ema_start", "ema_end"):
            check_number(name, getattr(self, name), 0.0, 1.0, low_open=True)
        check_number("center_momentum", self.center_momentum, 0.0, 1.0, low_open=True, high_open=True)
        check_device(self.device, "device")
        if self.nnodes > 1 and not self.master_addr:
            raise ValueError("master_addr: a multi-node run (nnodes > 1) needs the rank-0 machine's address")
        check_int("master_port", self.master_port, 1, 65535)

    @property
    def groups(self) -> tuple[str, ...]:
        return parse_groups(self.modalities, self.encoder)

    def head_sizes(self) -> tuple[int, int]:
        hidden, k = HEAD_SIZES.get(self.size, (2048, 65536))
        return self.head_hidden or hidden, self.prototypes or k  # None: by size


RESUMABLE_CHANGES = {"out", "cache", "resume", "progress", "num_workers", "device", "precision", "torch_threads",
                     "checkpoint_every", "keep_checkpoints", "log_every", "nproc_per_node", "nnodes", "node_rank",
                     "master_addr", "master_port"}
"""Config fields that may differ between a run and its resumption (run-time options, not the training math;
a different device, precision or number of processes continues correctly but not bit-identically)."""


def load_config(path: str | Path) -> Config:
    """The Config a run saved (``<out>/config.json``)."""
    return from_jsonable(Config, json.loads(Path(path).read_text()))
