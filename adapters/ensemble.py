"""Adapter ensembles: several tactile adapters of one student whose corrections are added with fixed weights.

    z_hat = phi(history) + sum_k w_k * c_k(touch)         (w_k a number, or one number per dimension of z)

Adapters that read different modalities, or were trained by different recipes, can be wrong in different ways; a
weighted mean of their corrections (weights 1/K) is the plain ensemble. An ensemble bundle is a directory::

    <ensemble>/config.json   EnsembleConfig: kind "adapter-ensemble", the members (adapter bundle references with
                             their weights), the touch refresh period, a free-form card
    <ensemble>/members/<m>/  the member adapter bundles, when copied in (``rotate ensemble-adapters``' default)

A member is a path relative to the ensemble's directory (members shipped inside it, e.g.
``members/imu_pressure_tracking``), any other path, or the name of a shipped adapter. Each member loads as its own
checked adapter bundle (its student and encoder digests, adapters.bundle.load_adapter); all must correct the same
student and read the same sensor samples (the four Digit 360 fingertips, or the Xela skin). Each member keeps its
own encoder restricted to its own modalities (a modality subset is encoded on its own: Sparsh-X fuses the modalities
it is given), so the ensemble reads the union of its members' windows and costs the sum of their encoder passes,
except that a member whose modalities are among the first member's, on the same encoder weights, starts from the
first member's unimodal layers and runs only its own fusion layers (:func:`shares_unimodal`; the same tokens bit for
bit).

Loaded, an ensemble is an :class:`EnsemblePolicy`: the same interface as ``AdaptedPolicy`` (``config``,
``act``/``act_batch`` with a correction, ``correction(windows, obs)``, ``fingers``, ``windows``, ``touch_every``),
so ``rotate evaluate --policy NAME=DIR``, ``rotate view`` and ``rotate deploy --policy DIR`` take it as they take
an adapter. Every member refreshes together, every ``touch_every`` steps (the members' own periods are not used);
a member that cannot read its touch makes the whole refresh unusable (the student alone), as one adapter's does.

Put one together (each member is checked; by default copied into the new bundle, so it stands alone and a member
retrained later in place does not change it)::

    rotate ensemble-adapters --members adapter runs/adapter_ip --out runs/ensemble        # weights 1/2 and 1/2
    rotate ensemble-adapters --members adapter runs/adapter_ip --weights 0.7 0.3 --out runs/ensemble_73
    rotate evaluate --policy adapter --policy ensemble=runs/ensemble --suite perturbations

Weights can also be per dimension of the latent (``--dim-weights``, K x Z numbers): member k's correction of
dimension d is weighted ``w_k * dim_weights_k[d]``, so each member can correct the directions of z it knows best
(``scripts/latent_sensitivity.py`` shows which dimensions friction and mass move).

A gate can make some dimensions' correction conditional on what the rest of the correction says (``--gate-dims``,
``--gate-signal``, ``--gate-width``; :class:`CorrectionGate`). With c the weighted sum above, the gate reads
``g = clip(signal . c / width, 0, 1)`` and multiplies the correction of the gated dimensions by g. For example, z[1]
(the direction the teacher's encoder moves for grippy cups) can be corrected only as far as the ensemble's own z[3]
and z[4] corrections read the cup as slippery (docs/results/adapter/gated_z1)::

    rotate ensemble-adapters --members adapter runs/adapter_ip --gate-dims 1 --gate-signal 0 0 0 -1 -1 0 0 0 \
        --gate-width 0.2 --out runs/gated
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from adapters.bundle import (
    AdaptedPolicy,
    TouchUnavailable,
    adapter_dir,
    check_bundle_header,
    load_adapter,
    read_adapter,
    run_traced,
)
from envs.validation import check_int, check_output_dir, check_types
from rotation.configs import from_jsonable, to_jsonable
from rotation.policy.bundle import BundleConfig, BundleError

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
    card: dict[str, Any] = field(default_factory=dict)
    """Free-form metadata: how it was put together, its evaluation."""
    gate: CorrectionGate | None = None
    """Optional gate on some dimensions' correction (None: every dimension as weighted)."""
    kind: str = KIND
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        check_bundle_header("adapter ensemble", self.kind, KIND, self.format_version, FORMAT_VERSION, self.touch_every)
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


def _config_path(path: Path) -> Path:
    return path / CONFIG_FILE


def is_ensemble_dir(path: str | Path) -> bool:
    """True when ``path`` (a directory or a shipped name) holds an adapter ensemble."""
    try:
        return json.loads(_config_path(adapter_dir(path)).read_text()).get("kind") == KIND
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
        data = json.loads(_config_path(path).read_text())
        members = data.get("members")
        if not isinstance(members, list) or not all(isinstance(m, dict) for m in members):
            raise ValueError("'members' must be a list of {\"adapter\": ..., \"weight\": ...}")
        data["members"] = tuple(from_jsonable(EnsembleMember, m) for m in members)
        cfg = from_jsonable(EnsembleConfig, data)
    except (TypeError, ValueError, KeyError) as err:
        raise BundleError(f"{_config_path(path)}: {err}") from None
    return path, cfg


def ensemble_digest(name_or_path: str | Path) -> str:
    """First 16 hex digits of the SHA-256 of the ensemble's config and every member's weights and config (what its
    actions depend on, for rotation.evaluate.finished)."""
    from adapters.bundle import WEIGHTS_FILE

    path, cfg = read_ensemble(name_or_path)
    h = hashlib.sha256(_config_path(path).read_bytes())
    for m in cfg.members:
        member, _, _ = read_adapter(member_path(path, m.adapter))
        h.update((member / WEIGHTS_FILE).read_bytes() + (member / CONFIG_FILE).read_bytes())
    return h.hexdigest()[:16]


class EnsemblePolicy:
    """Several adapters of one student acting as one: the student's latent plus the weighted sum of their
    corrections. Acts like :class:`adapters.bundle.AdaptedPolicy` (the first member's student acts)."""

    def __init__(self, cfg: EnsembleConfig, members: list[AdaptedPolicy], path: str | None = None) -> None:
        if len(members) != len(cfg.members):
            raise BundleError(f"ensemble: {len(cfg.members)} members configured, {len(members)} given")
        lead = members[0]
        for m in members[1:]:
            if m.adapter_config.student_sha256 != lead.adapter_config.student_sha256:
                raise BundleError(f"ensemble members correct different students: {lead.adapter_config.student} "
                                  f"({lead.adapter_config.student_sha256}) and {m.adapter_config.student} "
                                  f"({m.adapter_config.student_sha256})")
            if m.fingers != lead.fingers or m.env_needs != lead.env_needs:
                raise BundleError(f"ensemble members read different touch: {list(lead.fingers)} {lead.env_needs} and "
                                  f"{list(m.fingers)} {m.env_needs}")
        latent_dim = lead.student.config.latent_dim
        for m in cfg.members:
            if m.dim_weights and len(m.dim_weights) != latent_dim:
                raise BundleError(f"ensemble member {m.adapter!r}: {len(m.dim_weights)} dim_weights for a "
                                  f"{latent_dim}-dimensional latent")
        if cfg.gate is not None:
            cfg.gate.check(latent_dim, BundleError)
        self.ensemble_config = cfg
        self.members = members
        # (Z,) factor per member: weight x dim_weights (or weight on every dimension)
        self.weights = tuple(torch.full((latent_dim,), float(m.weight)) if not m.dim_weights else
                             float(m.weight) * torch.tensor(m.dim_weights, dtype=torch.float32) for m in cfg.members)
        self.shares = tuple(k > 0 and shares_unimodal(lead, m) for k, m in enumerate(members))
        """Per member: whether it takes the first member's unimodal pass (the first member itself: False)."""
        self.shared_pass = SharedPass(lead.encoder, [m.encoder for k, m in enumerate(members)
                                                     if k == 0 or self.shares[k]]) if any(self.shares) else None
        """The first member's unimodal layers and the fusion layers of it and of the members sharing them."""
        self.traced_shared: dict | None = None
        """Traces of :attr:`shared_pass` by input shapes once :meth:`prepare_realtime` ran (deploy); None: eager."""
        self.student = lead.student
        encoders = " + ".join(dict.fromkeys(f"{m.adapter_config.encoder} ({', '.join(m.adapter_config.modalities)})"
                                            for m in members))
        self.config: BundleConfig = replace(lead.student.config, adapter=path or "(in memory)", touch_encoder=encoders,
                                            card=dict(cfg.card))

    # ------------------------------------------------------------------ touch
    @property
    def fingers(self) -> tuple[str, ...]:
        return self.members[0].fingers

    @property
    def touch_every(self) -> int:
        return self.ensemble_config.touch_every

    @property
    def windows(self) -> tuple[str, ...]:
        """The union of the members' windows, in the order they first appear."""
        return tuple(dict.fromkeys(w for m in self.members for w in m.windows))

    @property
    def sensor(self) -> str:
        return self.members[0].sensor

    @property
    def env_needs(self) -> dict[str, Any]:
        return self.members[0].env_needs

    def env_windows(self, obs: Mapping[str, Any], idx: np.ndarray | None = None) -> dict[str, dict[str, Any]]:
        if self.sensor == "skin":
            return self.members[0].env_windows(obs, idx)
        tactile = obs["tactile"] if idx is None else obs["tactile"][idx]
        return {f: {w: tactile[f][w] for w in self.windows} for f in self.fingers}

    @staticmethod
    def _part(windows: Mapping[str, Mapping[str, Any]], member: AdaptedPolicy) -> dict[str, dict[str, Any]]:
        """The windows one member reads (it checks that they are there)."""
        names = set(member.windows) | ({"audio_wave"} if "audio" in member.windows else set())
        return {f: {w: x for w, x in ws.items() if w in names} for f, ws in windows.items() if ws is not None}

    def tokens(self, windows: Mapping[str, Mapping[str, Any]]) -> list[dict[str, dict[str, torch.Tensor]]]:
        """Each member's encoder tokens; TouchUnavailable as one adapter's. Members that share the first member's
        unimodal layers (:func:`shares_unimodal`) take its unimodal pass and run only their own fusion layers."""
        if not any(self.shares):
            return [m.tokens(self._part(windows, m)) for m in self.members]
        lead = self.members[0]
        lead_windows = self._part(windows, lead)
        lead.check_windows(lead_windows)  # the lead reads every window its sharing members read
        out = []
        with torch.no_grad():
            inputs, n = lead.encoder_inputs(lead_windows)
            try:
                fused = iter(self.shared_pass(inputs) if self.traced_shared is None else
                             run_traced(self.shared_pass, inputs, self.traced_shared))
            except ValueError as err:  # non-finite or malformed windows
                raise TouchUnavailable(str(err)) from None
            for m, shared in zip(self.members, self.shares, strict=True):
                if m is lead or shared:
                    out.append(m.per_finger(next(fused), n))
                else:
                    out.append(m.tokens(self._part(windows, m)))
        return out

    @torch.no_grad()
    def correction(self, windows: Mapping[str, Mapping[str, Any]], obs: Mapping[str, Any]) -> np.ndarray:
        """(N, Z) weighted sum of the members' corrections (per latent dimension where a member has dim_weights);
        TouchUnavailable when a member's touch is missing or the result is not finite."""
        z = self.members[0].student_latent(obs)
        total = sum(w * m.adapter(tokens, z, m.tracking(obs)) for w, m, tokens in
                    zip(self.weights, self.members, self.tokens(windows), strict=True))
        if self.ensemble_config.gate is not None:
            total = self.ensemble_config.gate.apply(total)
        if not torch.isfinite(total).all():
            raise TouchUnavailable("non-finite touch embeddings")
        return total.numpy()

    # ------------------------------------------------------------------ acting (the first member's student)
    def act_batch(self, obs: Mapping[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        return self.members[0].act_batch(obs, correction)

    def act(self, obs: Mapping[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        return self.members[0].act(obs, correction)

    def latent(self, obs: Mapping[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        return self.members[0].latent(obs, correction)

    def student_latent(self, obs: Mapping[str, Any]) -> torch.Tensor:
        return self.members[0].student_latent(obs)

    def proprio_features(self, obs: Mapping[str, Any]) -> torch.Tensor:
        return self.members[0].proprio_features(obs)

    def prepare_realtime(self) -> None:
        """Trace the acting paths (first member), and from the first refresh on every member's encoder and the
        shared pass (deploy): run eagerly, the shared pass gave the interpreter's lock back after each of its
        hundreds of operations, and the shipped ensemble's refreshes in the emulated deploy on a 2-core machine took
        1.2-1.5 s median, 0.7-0.9 s traced (docs/adapter.md; rotation.policy.bundle.trace_single)."""
        self.members[0].prepare_realtime()
        for m in self.members[1:]:
            m.traced_encoders = {}
        if self.shared_pass is not None:
            self.traced_shared = {}


class SharedPass(nn.Module):
    """The first member's unimodal layers once, then the fusion layers of each encoder in ``fusing`` (the first
    member's and those of the members sharing its unimodal layers): ``inputs -> (tokens of each, ...)``, one module
    that deploy can trace."""

    def __init__(self, lead: nn.Module, fusing: list[nn.Module]) -> None:
        super().__init__()
        self.lead = lead
        self.fusing = nn.ModuleList(fusing)

    def forward(self, inputs: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], ...]:
        xs = self.lead.unimodal(inputs)
        return tuple(enc.fuse({g: xs[g] for g in enc.modalities}) for enc in self.fusing)


def shares_unimodal(lead: AdaptedPolicy, member: AdaptedPolicy) -> bool:
    """True when ``member``'s encoder gives, for each of its modalities, the same unimodal-layer output as ``lead``'s:
    both Sparsh-X encoders with the same unimodal depth, ``member``'s modalities among ``lead``'s, and every one of
    ``member``'s weights and buffers equal to ``lead``'s (its register tokens row by row). Then ``member``'s encoder
    pass can start from ``lead``'s unimodal output: the same tokens, without running those layers twice."""
    a, b = lead.encoder, member.encoder
    if not all(hasattr(e, "unimodal") and hasattr(e, "fuse") for e in (a, b)) or lead.sensor != member.sensor:
        return False
    if not set(b.modalities) <= set(a.modalities) or len(a.blocks) != len(b.blocks):
        return False
    mine, theirs = b.state_dict(), a.state_dict()
    for key, value in mine.items():
        if key == "register_tokens":
            rows = [a.modalities.index(m) for m in b.modalities]
            if not torch.equal(value, theirs[key][rows]):
                return False
        elif key not in theirs or theirs[key].shape != value.shape or not torch.equal(theirs[key], value):
            return False
    return True


def load_ensemble(name_or_path: str | Path, device: str = "cpu") -> EnsemblePolicy:
    """Load an ensemble bundle, every member checked as ``load_adapter`` checks an adapter."""
    path, cfg = read_ensemble(name_or_path)
    members = []
    for m in cfg.members:
        where = member_path(path, m.adapter)
        try:
            members.append(load_adapter(where, device=device))
        except BundleError as err:
            raise BundleError(f"ensemble {path}: member {m.adapter!r}: {err}") from None
    return EnsemblePolicy(cfg, members, path=str(path))


@dataclass
class Config:
    members: tuple[str, ...] = ()
    """Adapter bundles to combine (shipped names or directories), all for the same student and the same sensors."""
    weights: tuple[float, ...] = ()
    """One weight per member (default 1/K each: the mean of the K corrections)."""
    dim_weights: tuple[float, ...] = ()
    """Per-latent-dimension factors on top of --weights: K x Z numbers, the first member's Z factors first (e.g. for
    two members and an 8-dimensional z, 16 numbers); empty: every dimension alike."""
    touch_every: int = 0
    """Control steps between touch refreshes (0: the first member's)."""
    gate_dims: tuple[int, ...] = ()
    """Latent dimensions whose correction is gated (empty: no gate); see --gate-signal and --gate-width."""
    gate_signal: tuple[float, ...] = ()
    """With --gate-dims: Z coefficients; the gate is clip(signal . correction / width, 0, 1) and scales the gated
    dimensions' correction (e.g. 0 0 0 -1 -1 0 0 0: open as far as z[3] and z[4] are corrected downwards)."""
    gate_width: float = 0.2
    """With --gate-dims: the signal that opens the gate fully."""
    copy: bool = True
    """Copy the members into OUT/members/ (the bundle stands alone); --no-copy references them where they are."""
    out: Path = Path("runs/ensemble")
    """The ensemble bundle's directory (refused if it already holds a bundle)."""

    def __post_init__(self) -> None:
        check_types(self)
        if not self.members:
            raise ValueError("--members: name at least one adapter bundle")
        if self.weights and len(self.weights) != len(self.members):
            raise ValueError(f"--weights: {len(self.weights)} weights for {len(self.members)} members")
        if any(not (math.isfinite(w) and 0 < w <= MAX_WEIGHT) for w in self.weights):
            raise ValueError(f"--weights must be in (0, {MAX_WEIGHT:g}], got {list(self.weights)}")
        if len(self.dim_weights) % len(self.members):
            raise ValueError(f"--dim-weights: {len(self.dim_weights)} numbers is not the same count for each of the "
                             f"{len(self.members)} members (K x Z numbers, the first member's first)")
        for k, part in enumerate(self.split_dim_weights()):
            check_dim_weights(part, f"--dim-weights of member {k + 1} ({self.members[k]})")
        check_int("touch_every", self.touch_every, 0, 10_000, unit="control steps")
        check_gate_width(self.gate_width, ValueError, "--gate-width")
        if bool(self.gate_dims) != bool(self.gate_signal):
            raise ValueError("--gate-dims and --gate-signal go together (give both or neither)")
        if self.gate_dims:
            self.gate().check(len(self.gate_signal), ValueError, "--gate-")
        check_output_dir("out", self.out)

    def gate(self) -> CorrectionGate | None:
        """The gate these options describe (None without --gate-dims)."""
        if not self.gate_dims:
            return None
        return CorrectionGate(tuple(self.gate_dims), tuple(float(v) for v in self.gate_signal), float(self.gate_width))

    def split_dim_weights(self) -> list[tuple[float, ...]]:
        """--dim-weights cut into each member's factors (empty tuples when not given)."""
        if not self.dim_weights:
            return [() for _ in self.members]
        z = len(self.dim_weights) // len(self.members)
        return [tuple(float(v) for v in self.dim_weights[k * z:(k + 1) * z]) for k in range(len(self.members))]


def run(cfg: Config) -> Path:
    """Write the ensemble bundle in ``cfg.out`` and load it once (every member checked); returns its directory."""
    if (cfg.out / CONFIG_FILE).exists():
        raise ValueError(f"{cfg.out} already holds a bundle; choose another --out (nothing is overwritten)")
    dirs = [read_adapter(ref)[0] for ref in cfg.members]  # adapter bundles (an ensemble is not a member)
    weights = cfg.weights or tuple(1.0 / len(dirs) for _ in dirs)
    if cfg.copy:
        names: list[str] = []
        for d in dirs:
            name = d.resolve().name
            while f"members/{name}" in names:
                name += "_"
            names.append(f"members/{name}")
    else:
        names = [str(d.resolve()) for d in dirs]
    touch_every = cfg.touch_every or read_adapter(dirs[0])[1].touch_every
    ens = EnsembleConfig(members=tuple(EnsembleMember(n, float(w), d) for n, w, d in
                                       zip(names, weights, cfg.split_dim_weights(), strict=True)),
                         touch_every=touch_every, gate=cfg.gate(),
                         card={"kind": KIND, "made_by": "rotate ensemble-adapters",
                               "members": {n: str(r) for n, r in zip(names, cfg.members, strict=True)}})
    cfg.out.mkdir(parents=True, exist_ok=True)
    try:
        if cfg.copy:
            for d, n in zip(dirs, names, strict=True):
                shutil.copytree(d, cfg.out / n)
        _config_path(cfg.out).write_text(json.dumps(to_jsonable(ens), indent=2) + "\n")
        policy = load_ensemble(cfg.out)
    except BaseException:
        shutil.rmtree(cfg.out / "members", ignore_errors=True)
        _config_path(cfg.out).unlink(missing_ok=True)
        raise
    print(f"adapter ensemble in {cfg.out}: {len(dirs)} members "
          + ", ".join(f"{r} x {w:g}" + (f" x [{', '.join(f'{v:g}' for v in d)}]" if d else "")
                      for r, w, d in zip(cfg.members, weights, cfg.split_dim_weights(), strict=True))
          + (f"; gate on z{list(ens.gate.dims)} by {list(ens.gate.signal)} / {ens.gate.width:g}" if ens.gate else "")
          + f"; touch every {touch_every} steps; windows {', '.join(policy.windows)}")
    return cfg.out
