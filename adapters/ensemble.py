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

`rotate ensemble-adapters` (adapters.ensemble_job) puts one together; its file format is adapters.ensemble_config.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from adapters.bundle import AdaptedPolicy, TouchUnavailable, load_adapter, run_traced
from adapters.ensemble_config import EnsembleConfig, member_path, read_ensemble
from rotation.policy.bundle_config import BundleConfig, BundleError


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
    def touch_smoothing(self) -> float:
        """How much of the held correction a refresh keeps (adapters.touch_delay.smooth)."""
        return float(self.ensemble_config.touch_smoothing)

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
    def start_correction(self, step: int) -> np.ndarray | None:
        return self.members[0].start_correction(step)

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
        1.2-1.5 s median, 0.7-0.9 s traced (docs/adapter.md; rotation.policy.actor.trace_single)."""
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
