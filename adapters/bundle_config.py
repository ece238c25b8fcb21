"""An adapter bundle on disk: its config.json (AdapterConfig: the student and encoder it reads, by name and
sha256, the modalities, the network, the refresh period), the files beside it, and how a name or directory
resolves to one.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from adapters.model import AdapterNetConfig
from adapters.touch_delay import check_smoothing
from rotation.configs import from_jsonable
from rotation.policy.bundle import resolve_bundle
from rotation.policy.bundle_config import BundleError
from rotation.tactile.models.encoders import SHIPPED_ENCODERS, shipped_encoders

KIND = "adapter"
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "adapter.safetensors"
FORMAT_VERSION = 1
SHIPPED_ADAPTERS = Path(__file__).resolve().parent.parent / "rotation" / "policies"
"""Adapter bundles ship beside the policy bundles (``rotation/policies/adapter``), so `--policy adapter` finds them."""

MODALITY_WINDOWS = {"img": "image", "mic": "audio", "imu": "imu", "pressure": "pressure"}
"""Sparsh-X token group -> the window (env `tactile` group, dataset, sensor) it is computed from."""
SKIN_SAMPLE = "hand"
"""The one sensor sample of a skin adapter (Sparsh-skin): the whole hand's Xela skin, the env's `skin` group."""


def check_bundle_header(what: str, kind: str, want_kind: str, version: int, want_version: int,
                        touch_every: Any, touch_smoothing: Any = 0.0) -> None:
    """BundleError unless a touch bundle's config.json is of ``want_kind``, in a format this version reads, with a
    refresh period of at least one control step and a smoothing factor in [0, 1)."""
    if kind != want_kind:
        raise BundleError(f"not an {what} (kind {kind!r})")
    if version != want_version:
        raise BundleError(f"{what} format {version} is not readable by this version (reads {want_version})")
    if isinstance(touch_every, bool) or not isinstance(touch_every, int) or touch_every < 1:
        raise BundleError(f"touch_every must be an integer >= 1, got {touch_every!r}")
    try:
        check_smoothing(touch_smoothing)
    except ValueError as err:
        raise BundleError(str(err)) from None


@dataclass(frozen=True)
class AdapterConfig:
    """What an adapter bundle's config.json holds."""

    student: str
    """The student bundle it corrects: a shipped name or a directory."""
    student_sha256: str
    """sha256 (first 16 hex digits) of the student's model.safetensors."""
    encoder: str
    """The frozen touch encoder: a shipped name (rotation/tactile/pretrained) or a checkpoint path."""
    encoder_sha256: str
    """sha256 (first 16 hex digits) of the encoder's weights file."""
    modalities: tuple[str, ...]
    """Encoder token groups it reads (img, mic, imu, pressure for Sparsh-X); the encoder is restricted to them."""
    net: AdapterNetConfig
    """Adapter network sizes."""
    touch_every: int = 4
    """Control steps between touch refreshes (the correction is held in between)."""
    touch_smoothing: float = 0.0
    """How much of the held correction a refresh keeps (adapters.touch_delay.smooth; 0: a refresh replaces it)."""
    card: dict[str, Any] = field(default_factory=dict)
    """Free-form metadata: training command, steps, evaluation."""
    kind: str = KIND
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        check_bundle_header("adapter bundle", self.kind, KIND, self.format_version, FORMAT_VERSION, self.touch_every,
                            self.touch_smoothing)
        if tuple(self.modalities) != tuple(n for n, _ in self.net.groups):
            raise BundleError(f"modalities {self.modalities} differ from the network's token groups "
                              f"{[n for n, _ in self.net.groups]}")


def file_digest(path: Path) -> str:
    """sha256 (first 16 hex digits) of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:16]


def student_weights(ref: str) -> Path:
    return resolve_bundle(ref) / "model.safetensors"


def encoder_weights(ref: str) -> Path:
    """The weights file of an encoder reference (shipped name, run directory or checkpoint file)."""
    path = Path(ref)
    if not path.exists() and ref in shipped_encoders():
        path = SHIPPED_ENCODERS / ref
    if path.is_dir():
        path = path / "encoder.safetensors"
    if not path.is_file():
        raise BundleError(f"no touch encoder at {ref!r} (shipped encoders: {', '.join(shipped_encoders()) or 'none'})")
    return path


def adapter_dir(name_or_path: str | Path) -> Path:
    """The directory of a shipped adapter's name (``rotation/policies/<name>``) when no directory of that path
    exists; else the path as given."""
    path = Path(name_or_path)
    if not path.is_dir() and (SHIPPED_ADAPTERS / str(name_or_path)).is_dir():
        return SHIPPED_ADAPTERS / str(name_or_path)
    return path


def is_adapter_dir(path: str | Path) -> bool:
    """True when ``path`` (a directory or a shipped name) holds an adapter bundle."""
    path = adapter_dir(path)
    cfg = path / CONFIG_FILE
    if not cfg.is_file() or not (path / WEIGHTS_FILE).is_file():
        return False
    try:
        return json.loads(cfg.read_text()).get("kind") == KIND
    except (OSError, ValueError):
        return False


def read_adapter(name_or_path: str | Path) -> tuple[Path, AdapterConfig, dict[str, torch.Tensor]]:
    """An adapter bundle's directory, config and weights, without resolving its student or encoder (what
    ``finetune-adapter --init-from`` starts from); :func:`load_adapter` is the checked way to use one."""
    path = adapter_dir(name_or_path)
    if not is_adapter_dir(path):
        members = sorted(d.name for d in (path / "members").glob("*") if is_adapter_dir(d))
        if members:  # an adapter ensemble (adapters.ensemble): its members are adapter bundles
            raise BundleError(f"{name_or_path}: an adapter ensemble, not one adapter; name one of its members: "
                              + ", ".join(str(path / "members" / m) for m in members))
        raise BundleError(f"{name_or_path}: not an adapter bundle (needs {CONFIG_FILE} with kind 'adapter' and "
                          f"{WEIGHTS_FILE})")
    try:
        cfg = from_jsonable(AdapterConfig, json.loads((path / CONFIG_FILE).read_text()))
    except (TypeError, ValueError, KeyError) as err:
        raise BundleError(f"{path / CONFIG_FILE}: {err}") from None
    try:
        weights = load_file(str(path / WEIGHTS_FILE))
    except (SafetensorError, OSError) as err:
        raise BundleError(f"{path / WEIGHTS_FILE}: {str(err).splitlines()[0]}") from None
    return path, cfg, weights
