"""Adapter bundles: a tactile adapter that names its student and touch encoder, loadable as a policy.

An adapter bundle is a directory::

    <adapter>/config.json          AdapterConfig: kind "adapter", the student and encoder references with the
                                   sha256 of their weights, the encoder's modalities, the adapter network's sizes,
                                   the touch refresh period, a free-form card
    <adapter>/adapter.safetensors  the adapter network's weights (g and the ZeroLinear)

It holds no copy of the student or the encoder: loading resolves both references (a shipped name or a path) and
refuses weights whose digest differs from the one the adapter was trained with. Loaded, it is an
:class:`AdaptedPolicy`, which acts like a policy bundle (``config``, ``act``, ``act_batch``, ``latent``) and adds
touch::

    policy = load_adapter("adapter")                       # shipped, or a directory
    corr = policy.correction(windows, obs)                 # {finger: {image, audio, imu, pressure}} -> (N, Z)
    corr = policy.correction(policy.env_windows(obs), obs) # the same from an env observation
    actions = policy.act_batch(obs, correction=corr)       # z = phi(history) + corr; corr None = the student

The correction is refreshed every ``touch_every`` control steps and held in between (touch tells friction and
mass, which change slowly; rendering and encoding four fingertips every step would cost more than the step).
Without a correction (no touch yet, a stalled sensor, non-finite embeddings) the policy is exactly its student.

Two kinds of touch, decided by the encoder (``AdaptedPolicy.sensor``): Sparsh-X reads one sample per Digit 360
fingertip (the env's `tactile` group, the deploy readers); Sparsh-skin reads one sample for the whole hand,
``{SKIN_SAMPLE: {"skin": (N, 10, 368, 6)}}`` (the env's `skin` group of the Xela hand). Simulation (fine-tuning,
evaluate, view) takes either; deploy and recorded sessions take Digit 360 adapters only.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import save_file
from torch import nn

from adapters.bundle_config import (
    CONFIG_FILE,
    FORMAT_VERSION,
    KIND,
    MODALITY_WINDOWS,
    SKIN_SAMPLE,
    WEIGHTS_FILE,
    AdapterConfig,
    encoder_weights,
    file_digest,
    read_adapter,
    student_weights,
)
from adapters.model import AdapterNetConfig, TouchAdapter, tracking_features
from rotation.configs import to_jsonable
from rotation.policy.actor import CorrectedActor, trace_single
from rotation.policy.bundle import PolicyBundle, load_policy_bundle
from rotation.policy.bundle_config import BundleConfig, BundleError, BundleRefused
from rotation.tactile.models.encoders import ENCODERS, kind_of, load_encoder


class TouchUnavailable(RuntimeError):
    """No usable touch for this step (a missing fingertip, a modality the sensors do not stream, non-finite
    embeddings); the caller acts as the student alone."""


def frozen_encoder(ref: str, modalities: tuple[str, ...], device: str = "cpu") -> nn.Module:
    """The touch encoder of ``ref`` restricted to ``modalities``, in eval mode with gradients off."""
    try:
        enc = load_encoder(ref, device=device)
    except ValueError as err:
        raise BundleError(str(err)) from None
    kind = kind_of(enc)
    try:
        enc = ENCODERS[kind].restrict(enc, tuple(modalities))
    except ValueError as err:
        raise BundleError(f"encoder {ref}: {err}") from None
    return enc.eval().requires_grad_(False)


class AdaptedPolicy:
    """A student with a tactile adapter: acts like a PolicyBundle, plus :meth:`correction` from touch windows."""

    def __init__(self, adapter_config: AdapterConfig, student: PolicyBundle, encoder: nn.Module,
                 adapter: TouchAdapter, path: str | None = None) -> None:
        student.require("adaptation", "an adapter corrects a student")
        if adapter.cfg.latent_dim != student.config.latent_dim:
            raise BundleError(f"adapter latent size {adapter.cfg.latent_dim} != the student's "
                              f"{student.config.latent_dim}")
        interface = encoder.token_interface
        if tuple(interface.groups) != tuple((n, c) for n, c in adapter.cfg.groups) or \
                interface.width != adapter.cfg.width:
            raise BundleError(f"the encoder's tokens {interface} do not fit the adapter (groups {adapter.cfg.groups}, "
                              f"width {adapter.cfg.width})")
        self.adapter_config = adapter_config
        self.student = student
        student.net.eval().requires_grad_(False)  # frozen: only the adapter ever learns
        self.encoder = encoder
        self.adapter = adapter.eval()
        self.corrected_actor = CorrectedActor(student.net)
        """The student's acting path with a correction (batches)."""
        self.corrected: nn.Module | None = None
        """``corrected_actor`` traced for one observation (:meth:`prepare_realtime`)."""
        self.traced_encoders: dict[tuple, nn.Module] | None = None
        """After :meth:`prepare_realtime`: the encoder traced per input shapes (:meth:`_encode`)."""
        self.config: BundleConfig = replace(student.config, adapter=path or "(in memory)",
                                            touch_encoder=adapter_config.encoder, card=dict(adapter_config.card))

    # ------------------------------------------------------------------ touch
    @property
    def fingers(self) -> tuple[str, ...]:
        """The sensor samples read per step (fingertips)."""
        return self.adapter.cfg.samples

    @property
    def touch_every(self) -> int:
        return self.adapter_config.touch_every

    @property
    def touch_smoothing(self) -> float:
        """How much of the held correction a refresh keeps (adapters.touch_delay.smooth)."""
        return float(self.adapter_config.touch_smoothing)

    @property
    def windows(self) -> tuple[str, ...]:
        """Window names per sample it needs (image, audio, imu, pressure; skin)."""
        return tuple(MODALITY_WINDOWS.get(m, m) for m in self.adapter_config.modalities)

    @property
    def sensor(self) -> str:
        """'digit360' (Sparsh-X, one sample per fingertip) or 'skin' (Sparsh-skin, one sample for the hand)."""
        return kind_of(self.encoder) if kind_of(self.encoder) == "skin" else "digit360"

    @property
    def env_needs(self) -> dict[str, Any]:
        """The EnvConfig fields a simulated env needs for this adapter's touch (the Digit 360 hand with its
        simulated fingertips, or the Xela hand with its skin)."""
        return {"hand": "xela", "skin": True} if self.sensor == "skin" else {"tactile": True}

    def env_windows(self, obs: Mapping[str, Any], idx: np.ndarray | None = None) -> dict[str, dict[str, Any]]:
        """The sensor samples of an env observation (of the envs ``idx``, default all), as :meth:`correction` takes
        them; a `tactile` group renders only what is read here."""
        if self.sensor == "skin":
            skin = obs["skin"] if idx is None else obs["skin"][idx]
            return {SKIN_SAMPLE: {"skin": skin}}
        tactile = obs["tactile"] if idx is None else obs["tactile"][idx]
        return {f: {w: tactile[f][w] for w in self.windows} for f in self.fingers}

    def tokens(self, windows: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, torch.Tensor]]:
        """{finger: {window: (N, ...)}} -> {finger: {group: (N, N_g, D)}} from the frozen encoder (one batched call);
        TouchUnavailable when a finger or window is missing."""
        self.check_windows(windows)
        inputs, n = self.encoder_inputs(windows)
        with torch.no_grad():
            try:
                out = self._encode(inputs)
            except ValueError as err:  # non-finite or malformed windows
                raise TouchUnavailable(str(err)) from None
        return self.per_finger(out, n)

    def check_windows(self, windows: Mapping[str, Mapping[str, Any]]) -> None:
        """TouchUnavailable when a finger or one of its windows is missing."""
        missing = [f for f in self.fingers if f not in windows or windows[f] is None]
        if missing:
            raise TouchUnavailable(f"no touch from {', '.join(missing)}")
        gaps = [f"{f}/{w}" for f in self.fingers for w in self.windows if w not in windows[f] and
                not (w == "audio" and "audio_wave" in windows[f])]
        if gaps:
            raise TouchUnavailable(f"missing touch windows {', '.join(gaps)}")

    def encoder_inputs(self, windows: Mapping[str, Mapping[str, Any]]) -> tuple[dict[str, torch.Tensor], int]:
        """The encoder's preprocessed inputs for every finger in one batch ({group: (F * N, ...)}) and N."""
        batches = [self.encoder.preprocess(windows[f]) for f in self.fingers]
        n = next(iter(batches[0].values())).shape[0]
        return {g: torch.cat([b[g] for b in batches]) for g in batches[0]}, n  # (F * N, ...)

    def per_finger(self, out: Mapping[str, torch.Tensor], n: int) -> dict[str, dict[str, torch.Tensor]]:
        """{group: (F * N, N_g, D)} -> {finger: {group: (N, N_g, D)}}."""
        return {f: {g: t[i * n:(i + 1) * n] for g, t in out.items()} for i, f in enumerate(self.fingers)}

    def _encode(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The frozen encoder's tokens; after :meth:`prepare_realtime`, from the encoder traced for these input
        shapes (traced on first use; the values are the eager encoder's, the finite check is done here since a
        trace keeps no Python checks)."""
        if self.traced_encoders is None:
            return self.encoder(inputs)
        return run_traced(self.encoder, inputs, self.traced_encoders)

    @torch.no_grad()
    def student_latent(self, obs: Mapping[str, Any]) -> torch.Tensor:
        """phi(history): (N, Z) for batched observations."""
        t = self.student._tensors(dict(obs), batched=True)
        return self.student.net.extractor.z(t)

    @property
    def proprio_dim(self) -> int:
        """Width of :meth:`proprio_features`."""
        return self.student.net.extractor.features_dim - self.student.config.latent_dim

    @torch.no_grad()
    def proprio_features(self, obs: Mapping[str, Any]) -> torch.Tensor:
        """The student's actor input besides the latent, (N, S * D), for batched observations (the adapter's
        action-matching loss feeds it to ``student.net.head``)."""
        return self.student.net.proprio_features(self.student._tensors(dict(obs), batched=True))

    @torch.no_grad()
    def tracking(self, obs: Mapping[str, Any]) -> torch.Tensor:
        """(N, 48) joint tracking features of the batched observation's ``proprio_hist`` for an adapter that reads
        them (adapters.model.tracking_features), (N, 0) for one that does not."""
        if not self.adapter.cfg.tracking:
            return torch.zeros(len(obs["proprio_hist"]), 0)
        return tracking_features(self.student._tensors(dict(obs), batched=True)["proprio_hist"])

    @torch.no_grad()
    def correction(self, windows: Mapping[str, Mapping[str, Any]], obs: Mapping[str, Any]) -> np.ndarray:
        """(N, Z) latent correction from touch windows and the batched observation (for phi, and the joint
        tracking where the adapter reads it); TouchUnavailable when touch is missing or the result is not finite."""
        corr = self.adapter(self.tokens(windows), self.student_latent(obs), self.tracking(obs))
        if not torch.isfinite(corr).all():
            raise TouchUnavailable("non-finite touch embeddings")
        return corr.numpy()

    # ------------------------------------------------------------------ acting (PolicyBundle's interface)
    def start_correction(self, step: int) -> np.ndarray | None:
        """The student's cautious start (PolicyBundle.start_correction): added under the touch correction."""
        return self.student.start_correction(step)

    @torch.no_grad()
    def act_batch(self, obs: Mapping[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        """(N, 16) actions; without a correction exactly the student's."""
        if correction is None:
            return self.student.act_batch(dict(obs))
        t = self.student._tensors(dict(obs), batched=True)
        return self.corrected_actor(t, torch.as_tensor(correction, dtype=torch.float32)).numpy()

    def prepare_realtime(self) -> None:
        """Trace the student's acting paths, with and without a correction, for single observations, and from the
        first touch refresh on the encoder (deploy; see rotation.policy.actor.trace_single); :meth:`act` and
        :meth:`correction` then use them."""
        self.traced_encoders = {}
        self.student.prepare_realtime()
        example = self.student._tensors(self.config.zero_observation(), batched=False)
        self.corrected = trace_single(self.corrected_actor, (example, torch.zeros(1, self.student.config.latent_dim)))

    @torch.no_grad()
    def act(self, obs: Mapping[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        """One observation (no batch dim) -> (16,) action; ``correction`` (Z,) or (1, Z)."""
        corr = None if correction is None else np.asarray(correction, np.float32).reshape(1, -1)
        if self.corrected is not None:
            if corr is None:
                return self.student.act(dict(obs))
            tensors = self.student._tensors(dict(obs), batched=False)
            return self.corrected(tensors, torch.as_tensor(corr)).numpy()[0]  # as PolicyBundle.act
        batched = {k: np.asarray(obs[k])[None] for k in self.config.obs_groups}
        return self.act_batch(batched, corr)[0]

    def latent(self, obs: Mapping[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        z = self.student.latent(dict(obs))
        return z if correction is None else z + np.asarray(correction, np.float32).reshape(z.shape)

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        tensors = {k: v.detach().cpu().contiguous() for k, v in self.adapter.state_dict().items()}
        bad = [k for k, v in tensors.items() if not torch.isfinite(v).all()]
        if bad:
            raise BundleError(f"refusing to save an adapter with non-finite weights: {bad}")
        save_file(tensors, str(path / WEIGHTS_FILE), metadata={"kind": KIND, "format_version": str(FORMAT_VERSION)})
        (path / CONFIG_FILE).write_text(json.dumps(to_jsonable(self.adapter_config), indent=2) + "\n")
        self.config = replace(self.config, adapter=str(path))
        return path


def run_traced(module: nn.Module, inputs: dict[str, torch.Tensor], traced: dict) -> Any:
    """``module(inputs)`` from its trace for these input shapes, traced on first use into ``traced`` (keyed by the
    inputs' names and shapes; rotation.policy.actor.trace_single). A trace keeps no Python checks, so the eager
    module's ValueError on non-finite inputs is raised here first."""
    bad = [g for g, x in inputs.items() if not bool(torch.isfinite(x).all())]
    if bad:
        raise ValueError(f"non-finite values (NaN or inf) in the touch input(s) {bad}")
    key = tuple((g, tuple(x.shape)) for g, x in inputs.items())
    if key not in traced:
        traced[key] = trace_single(module, (inputs,))
    return traced[key](inputs)


def build_adapted(student: str, encoder: str, modalities: tuple[str, ...], touch_every: int = 4,
                  hidden: tuple[int, ...] = (256, 128), with_latent: bool = True, seed: int = 0,
                  device: str = "cpu", tracking: bool = False, touch: bool = True) -> AdaptedPolicy:
    """A fresh adapter (zero correction) for ``student`` reading ``encoder`` restricted to ``modalities``: a
    Sparsh-X encoder reads the four fingertips, a Sparsh-skin encoder the whole hand (one sample). ``touch`` False:
    a blind adapter (adapters.model.AdapterNetConfig.touch), the ablation without touch."""
    from envs.constants import FINGERS

    student_bundle = load_policy_bundle(student)
    enc = frozen_encoder(encoder, modalities, device)
    interface = enc.token_interface
    samples = (SKIN_SAMPLE,) if kind_of(enc) == "skin" else tuple(FINGERS)
    torch.manual_seed(seed)
    net = AdapterNetConfig(samples=samples, groups=tuple(interface.groups), width=interface.width,
                           latent_dim=student_bundle.config.latent_dim, hidden=tuple(hidden), with_latent=with_latent,
                           tracking=tracking, touch=touch)
    cfg = AdapterConfig(student=student, student_sha256=file_digest(student_weights(student)), encoder=encoder,
                        encoder_sha256=file_digest(encoder_weights(encoder)), modalities=tuple(interface.names),
                        net=net, touch_every=touch_every)
    return AdaptedPolicy(cfg, student_bundle, enc, TouchAdapter(net).to(device))


def load_adapter(name_or_path: str | Path, device: str = "cpu") -> AdaptedPolicy:
    """Load an adapter bundle (a directory or a shipped name), resolving and checking its student and encoder."""
    path, cfg, state = read_adapter(name_or_path)
    for what, ref, want, weights in (("student", cfg.student, cfg.student_sha256, student_weights),
                                     ("encoder", cfg.encoder, cfg.encoder_sha256, encoder_weights)):
        try:
            got = file_digest(weights(ref))
        except BundleError as err:
            raise BundleRefused(f"adapter {path}: its {what} {ref!r} cannot be found ({err})") from None
        if got != want:
            raise BundleRefused(f"adapter {path} was trained for the {what} {ref!r} with weights sha256 {want}, but "
                                f"{ref!r} now has {got}: retrain the adapter for this {what}")
    student = load_policy_bundle(cfg.student)
    encoder = frozen_encoder(cfg.encoder, cfg.modalities, device)
    adapter = TouchAdapter(cfg.net)
    try:
        adapter.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise BundleError(f"{path / WEIGHTS_FILE}: {str(err).splitlines()[0]}") from None
    return AdaptedPolicy(cfg, student, encoder, adapter.to(device), path=str(path))
