"""The config of `rotate probe` and the tasks it can probe: each task's label, head size, loss and metrics, for
Sparsh-X and Sparsh-skin.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from envs.constants import FINGERS, PRIV_FIELDS
from envs.oas import ACTIONS, SURFACES
from envs.oas import OBJECTS as OAS_OBJECTS
from envs.shake_contents import CONTENT_NAMES, FILL_LEVELS
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.data.dataset import check_fingers, check_session_sources
from rotation.tactile.probes.data import (
    Task,
)
from rotation.tactile.probes.skin import (
    force_metrics,
    joystick_metrics,
    pose_metrics,
    relative_pose,
)
from rotation.tactile.runtime import (
    check_device,
)

VARIANTS = ("pretrained", "e2e", "image_only")
"""Sparsh-X's variants (Sparsh-skin has no image tokens: pretrained and e2e)."""
MODALITY_VARIANTS = {"all": None, "image": ("img",), "audio": ("mic",), "imu": ("imu",), "pressure": ("pressure",)}
"""Sparsh-X's frozen encoder reading every modality's tokens ('all', the same as 'pretrained') or one modality's:
the variants of the touch benchmarks (shake, object-action-surface), by the names their reports use."""
BENCHMARK_VARIANTS = (*MODALITY_VARIANTS, "e2e")
"""The default variants of a run of touch-benchmark tasks."""
BENCHMARKS = {"shake": ("shake_content", "shake_fill"), "oas": ("oas_object", "oas_action", "oas_surface")}
"""A benchmark name given as a task stands for its tasks."""
CLASS_NAMES = {"shake_content": CONTENT_NAMES, "shake_fill": FILL_LEVELS, "oas_object": tuple(OAS_OBJECTS),
               "oas_action": ACTIONS, "oas_surface": SURFACES}
"""Class names of the multi-class tasks (their confusion matrices' axes)."""


def _rmse(pred: np.ndarray, target: np.ndarray) -> float:
    return float(np.sqrt(np.mean((pred - target) ** 2)))


def balanced_accuracy(pred: np.ndarray, target: np.ndarray, classes: int = 2) -> float:
    """Mean of the recall of each class present in ``target`` (class ids 0 .. classes - 1)."""
    recalls = [float(np.mean(pred[target == c] == c)) for c in range(classes) if np.any(target == c)]
    return float(np.mean(recalls)) if recalls else float("nan")


def class_metrics(classes: int):
    """Accuracy and balanced accuracy of (N, 1) predicted and true class ids."""
    def metrics(p: np.ndarray, t: np.ndarray) -> dict[str, float]:
        return {"accuracy": float(np.mean(p[:, 0] == t[:, 0])),
                "balanced_accuracy": balanced_accuracy(p[:, 0], t[:, 0], classes)}
    return metrics


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
    "shake_content": Task("content", len(CONTENT_NAMES), False, lambda y, _: y[:, :1],
                          class_metrics(len(CONTENT_NAMES)), classes=len(CONTENT_NAMES)),
    "shake_fill": Task("fill", len(FILL_LEVELS), False, lambda y, _: y[:, :1], class_metrics(len(FILL_LEVELS)),
                       classes=len(FILL_LEVELS)),
    **{f"oas_{label}": Task(label, len(names), False, lambda y, _: y[:, :1], class_metrics(len(names)),
                            classes=len(names))
       for label, names in (("object", tuple(OAS_OBJECTS)), ("action", ACTIONS), ("surface", SURFACES))},
}
"""Sparsh-X task name -> definition (see the module docstring)."""
SKIN_TASKS: dict[str, Task] = {
    "force": Task("skin_force", 54, False, lambda y, _: y.reshape(y.shape[0], -1), force_metrics, loss="smooth_l1"),
    "pose": Task("object_pose", 6, False, lambda y, _: relative_pose(y), pose_metrics, temporal=True),
    "joystick": Task("joystick", 3, False, lambda y, _: y, joystick_metrics, temporal=True),
}
"""Sparsh-skin task name -> definition (rotation.tactile.probes.skin)."""
ENCODER_TASKS = {"sparshx": TASKS, "skin": SKIN_TASKS}
ENCODER_VARIANTS = {"sparshx": VARIANTS + tuple(MODALITY_VARIANTS), "skin": ("pretrained", "e2e")}


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
    """Tasks: Sparsh-X force, contact_force, slip, mass, friction, the shaking benchmark's shake_content, shake_fill
    ('shake': both) and object-action-surface's oas_object, oas_action, oas_surface ('oas': all three); skin force,
    pose, joystick. None: every task of the encoder whose label all the
    sessions hold (skin cup sessions: force, pose; joystick sessions: force, joystick)."""
    variants: tuple[str, ...] | None = None
    """Variants among pretrained (frozen), e2e (trained end to end from scratch), image_only (Sparsh-X: frozen,
    image tokens); for the touch benchmarks all (frozen, every modality: pretrained), image, audio, imu, pressure
    (frozen, that modality's tokens). None: the encoder's first three, or for benchmark tasks all, image, audio, imu,
    pressure and e2e."""
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
    token_cache_gb: float = 8.0
    """Frozen variants: compute the encoder's tokens of every window once and train the probes on them, when they
    take at most this many GB of memory (float32; 0: run the encoder in every step). Exact: a frozen encoder gives
    a window the same tokens each time."""
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
        if self.tasks is not None:  # a benchmark's name stands for its tasks
            object.__setattr__(self, "tasks", tuple(dict.fromkeys(
                t for name in self.tasks for t in BENCHMARKS.get(name, (name,)))))
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
        check_number("token_cache_gb", self.token_cache_gb, 0.0, 1e6, unit="GB")
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
    def benchmark(self) -> bool:
        """Every task is a touch benchmark's (shake_*)."""
        return self.tasks is not None and all(t.startswith(tuple(BENCHMARKS)) for t in self.tasks)

    @property
    def variant_names(self) -> tuple[str, ...]:
        if self.variants is not None:
            return self.variants
        if self.benchmark:
            return BENCHMARK_VARIANTS
        return VARIANTS if self.encoder == "sparshx" else ENCODER_VARIANTS[self.encoder]
