"""An adapter ensemble on disk: its config.json (EnsembleConfig: the members with their weights, per-dimension
weights and an optional gate on the correction), how members resolve, and the ensemble's digest.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from adapters.bundle_config import adapter_dir, check_bundle_header, read_adapter
from rotation.configs import from_jsonable
from rotation.policy.bundle_config import BundleError

KIND = "adapter-ensemble"
MAX_WEIGHT = 10.0
"""Largest member weight: far beyond 1 a correction is scaled past anything its adapter learned."""
CONFIG_FILE = "config.json"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class EnsembleMember:
    adapter: str
    """An adapter bundle: a path relative to the ensemble's directory, another path, or a shipped adapter's name."""
    weight: float
    """Its correction's weight (1/K for the plain mean of K members)."""
    dim_weights: tuple[float, ...] = ()
    """Optional per-latent-dimension factors (one per dimension of z, each in [0, MAX_WEIGHT], not all 0): the
    member's correction of dimension d is weighted ``weight * dim_weights[d]``. Empty: every dimension by ``weight``.
    With them, members that read different modalities can each correct the directions of z they know best."""


@dataclass(frozen=True)
class CorrectionGate:
    """The correction of ``dims`` applied only as far as the ensemble's own correction reads a condition: with c
    the weighted sum of the members' corrections, ``g = clip(sum_d signal[d] * c[d] / width, 0, 1)`` per sample,
    and the correction of each gated dimension is ``g * c[dim]``. A zero correction (adapters at initialization)
    stays exactly zero."""

    dims: tuple[int, ...]
    """Latent dimensions whose correction is gated (each in [0, Z))."""
    signal: tuple[float, ...]
    """One coefficient per latent dimension (Z numbers, not all 0, 0 on every gated dimension): what the gate reads
    of the correction. E.g. -1 on z[3] and z[4]: open as far as those corrections read the cup as slippery."""
    width: float
    """How much of the signal opens the gate fully (> 0; the gate is 0 at or below a signal of 0)."""

    def check(self, latent_dim: int, error: type[Exception] = ValueError, prefix: str = "gate ") -> None:
        """Refuse a gate that cannot act on a ``latent_dim``-dimensional z (``prefix`` names the fields: "gate "
        in a bundle, "--gate-" on the command line)."""
        dims, signal = self.dims, self.signal
        if (not isinstance(dims, tuple) or not dims or len(set(dims)) != len(dims)
                or not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d < latent_dim for d in dims)):
            raise error(f"{prefix}dims must be distinct latent dimensions in [0, {latent_dim}), got {dims!r}")
        if not isinstance(signal, tuple) or len(signal) != latent_dim or not all(
                not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) for v in signal):
            raise error(f"{prefix}signal must be {latent_dim} finite numbers, one per latent dimension, got {signal!r}")
        if not any(signal) or any(signal[d] for d in dims):
            raise error(f"{prefix}signal must read some dimension and none of the gated ones {list(dims)}, got "
                        f"{list(signal)}")
        check_gate_width(self.width, error, f"{prefix}width")

    def apply(self, correction: torch.Tensor) -> torch.Tensor:
        """(N, Z) correction with the gated dimensions scaled by the gate (a new tensor)."""
        signal = torch.tensor(self.signal, dtype=correction.dtype)
        g = torch.clamp(correction @ signal / float(self.width), 0.0, 1.0)
        out = correction.clone()
        out[:, list(self.dims)] *= g[:, None]
        return out


@dataclass(frozen=True)
class EnsembleConfig:
    """What an ensemble bundle's config.json holds."""

    members: tuple[EnsembleMember, ...]
    touch_every: int = 4
    """Control steps between touch refreshes (every member refreshes together; the correction is held between)."""
    touch_smoothing: float = 0.0
    """How much of the held correction a refresh keeps (adapters.touch_delay.smooth; 0: a refresh replaces it)."""
    card: dict[str, Any] = field(default_factory=dict)
    """Free-form metadata: how it was put together, its evaluation."""
    gate: CorrectionGate | None = None
    """Optional gate on some dimensions' correction (None: every dimension as weighted)."""
    kind: str = KIND
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        check_bundle_header("adapter ensemble", self.kind, KIND, self.format_version, FORMAT_VERSION, self.touch_every,
                            self.touch_smoothing)
        if not self.members or not all(isinstance(m, EnsembleMember) for m in self.members):
            raise BundleError(f"an adapter ensemble needs at least one member, got {self.members!r}")
        bad = [m.weight for m in self.members if isinstance(m.weight, bool) or not isinstance(m.weight, (int, float))
               or not (math.isfinite(m.weight) and 0 < m.weight <= MAX_WEIGHT)]
        if bad:
            raise BundleError(f"ensemble member weights must be numbers in (0, {MAX_WEIGHT:g}], got {bad}")
        for m in self.members:
            check_dim_weights(m.dim_weights, f"ensemble member {m.adapter!r}: dim_weights", BundleError)
        if self.gate is not None and not isinstance(self.gate, CorrectionGate):
            raise BundleError(f"ensemble gate must be {{\"dims\", \"signal\", \"width\"}}, got {self.gate!r}")


def check_gate_width(width: Any, error: type[Exception] = ValueError, what: str = "gate width") -> None:
    if isinstance(width, bool) or not isinstance(width, (int, float)) or not (math.isfinite(width)
                                                                              and 0 < width <= MAX_WEIGHT):
        raise error(f"{what} must be a number in (0, {MAX_WEIGHT:g}], got {width!r}")


def check_dim_weights(values: Any, what: str, error: type[Exception] = ValueError) -> None:
    """Per-dimension factors: a (possibly empty) tuple of finite numbers in [0, MAX_WEIGHT], not all 0."""
    if not isinstance(values, tuple) or not all(not isinstance(v, bool) and isinstance(v, (int, float))
                                                and math.isfinite(v) and 0 <= v <= MAX_WEIGHT for v in values):
        raise error(f"{what} must be numbers in [0, {MAX_WEIGHT:g}], one per latent dimension, got {values!r}")
    if values and not any(values):
        raise error(f"{what} are all 0: the member would correct nothing")


def config_path(path: Path) -> Path:
    return path / CONFIG_FILE


def is_ensemble_dir(path: str | Path) -> bool:
    """True when ``path`` (a directory or a shipped name) holds an adapter ensemble."""
    try:
        return json.loads(config_path(adapter_dir(path)).read_text()).get("kind") == KIND
    except (OSError, ValueError, AttributeError):
        return False


def member_path(ensemble_dir: Path, ref: str) -> Path:
    """Where a member's bundle is: inside the ensemble's directory first, then the reference as given (a path or a
    shipped adapter's name)."""
    inside = ensemble_dir / ref
    if not Path(ref).is_absolute() and inside.is_dir():
        return inside
    return adapter_dir(ref)


def read_ensemble(name_or_path: str | Path) -> tuple[Path, EnsembleConfig]:
    path = adapter_dir(name_or_path)
    if not is_ensemble_dir(path):
        raise BundleError(f"{name_or_path}: not an adapter ensemble (needs {CONFIG_FILE} with kind {KIND!r})")
    try:
        data = json.loads(config_path(path).read_text())
        members = data.get("members")
        if not isinstance(members, list) or not all(isinstance(m, dict) for m in members):
            raise ValueError("'members' must be a list of {\"adapter\": ..., \"weight\": ...}")
        data["members"] = tuple(from_jsonable(EnsembleMember, m) for m in members)
        cfg = from_jsonable(EnsembleConfig, data)
    except (TypeError, ValueError, KeyError) as err:
        raise BundleError(f"{config_path(path)}: {err}") from None
    return path, cfg


def ensemble_digest(name_or_path: str | Path) -> str:
    """First 16 hex digits of the SHA-256 of the ensemble's config and every member's weights and config (what its
    actions depend on, for rotation.evaluate.finished)."""
    from adapters.bundle_config import WEIGHTS_FILE

    path, cfg = read_ensemble(name_or_path)
    h = hashlib.sha256(config_path(path).read_bytes())
    for m in cfg.members:
        member, _, _ = read_adapter(member_path(path, m.adapter))
        h.update((member / WEIGHTS_FILE).read_bytes() + (member / CONFIG_FILE).read_bytes())
    return h.hexdigest()[:16]
