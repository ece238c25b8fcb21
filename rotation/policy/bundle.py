"""The policy bundle: the one artifact that goes from training to evaluation, the demo and the robot.

A bundle is a directory::

    <bundle>/config.json        BundleConfig: format and env version, network sizes, observation groups read,
                                latent source, normalization settings, joint limits, action scale, control rate,
                                optional adapter / touch-encoder references, free-form ``card`` metadata
    <bundle>/model.safetensors  every tensor needed to act, the observation normalization statistics included
                                (``extractor.proprio_norm.{mean,var,count}``, ...), so nothing outside re-declares them

Acting is deterministic: the Gaussian policy's mean, clipped to [-1, 1] (what the env and the hand clip to anyway).
The acting network is ``features = cat(flatten(norm(proprio)), z)`` -> actor MLP (ELU) -> linear mean, with z from
the env-factor encoder over ``priv`` (teacher, ``latent_source="privileged"``) or from the adaptation module over
``proprio_hist`` (student, ``latent_source="adaptation"``).

    bundle = load_policy_bundle("student")     # a bundle shipped in rotation/policies/, or a directory
    action = bundle.act(obs)                   # {"proprio": (3, 32), "proprio_hist": (30, 32)} -> (16,)
    actions = bundle.act_batch(batched_obs)    # leading N on every group -> (N, 16)
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from envs import constants as C
from rotation.configs import from_jsonable, to_jsonable
from rotation.policy.actor import ActorNet, trace_single
from rotation.policy.bundle_config import (
    CONFIG_FILE,
    ENV_VERSION,
    FORMAT_VERSION,
    ROLE,
    WEIGHTS_FILE,
    BundleConfig,
    BundleError,
    LatentSource,
)
from rotation.policy.features import PrivilegedExtractor, StudentExtractor
from rotation.policy.networks import AdaptationConfig

SHIPPED_DIR = Path(__file__).resolve().parent.parent / "policies"
"""Bundles shipped with the package: ``rotation/policies/<name>/``."""


class PolicyBundle:
    """A loaded bundle: :attr:`config` plus the acting network :attr:`net` (eval mode, CPU, float32)."""

    def __init__(self, config: BundleConfig, net: ActorNet | None = None) -> None:
        self.config = config
        self.net = (net if net is not None else ActorNet(config)).eval()
        self.single: nn.Module | None = None
        """``net`` traced for one observation (:meth:`prepare_realtime`); :meth:`act` uses it when set."""

    def prepare_realtime(self) -> None:
        """Trace the acting network for single observations (:func:`trace_single`); deploy calls this once before
        the control loop. :meth:`act` then runs the traced network; batches keep the eager one."""
        self.single = trace_single(self.net, (self._tensors(self.config.zero_observation(), batched=False),))

    # ------------------------------------------------------------------ acting
    def _tensors(self, obs: dict[str, Any], batched: bool) -> dict[str, torch.Tensor]:
        """Check the groups this policy reads (present, shape, finite) and convert them to float32 tensors."""
        if not isinstance(obs, dict):
            raise BundleError(f"observation must be a dict of named groups {sorted(self.config.obs_groups)}, "
                              f"got {type(obs).__name__}")
        missing = [k for k in self.config.obs_groups if k not in obs]
        if missing:
            raise BundleError(f"observation is missing group(s) {missing}; this policy reads "
                              f"{dict(self.config.obs_groups)} and got {sorted(obs)}")
        out, n = {}, None
        for key, shape in self.config.obs_groups.items():
            try:
                with np.errstate(over="ignore"):  # a value past float32's range becomes inf, refused below
                    a = np.asarray(obs[key], dtype=np.float32)
            except (TypeError, ValueError) as err:
                raise BundleError(f"observation group {key!r} is not an array of numbers: {err}") from None
            got = a.shape[1:] if batched else a.shape
            if got != shape or (batched and a.ndim != len(shape) + 1):
                want = f"(N, {', '.join(map(str, shape))})" if batched else str(shape)
                raise BundleError(f"observation group {key!r} has shape {a.shape}, expected {want}")
            if batched:
                if n is not None and a.shape[0] != n:
                    raise BundleError(f"observation groups disagree on the batch size: {key!r} has {a.shape[0]}, "
                                      f"others {n}")
                n = a.shape[0]
            # numpy, not torch, up to here: each torch op gives the interpreter's lock back and waits to take it
            # again, and in deploy the policy's thread, among a dozen busy driver threads, waited up to tens of ms
            # each time (rotate deploy: 8-15 held steps in 100, now 0-3)
            if not np.isfinite(a).all():
                raise BundleError(f"observation group {key!r} contains non-finite values (NaN or inf)")
            b = a if batched else a[None]
            out[key] = torch.from_numpy(b if b.flags.writeable else b.copy())  # torch wants a writeable array
        return out

    def require(self, source: LatentSource, who: str) -> PolicyBundle:
        """This bundle, if its latent comes from ``source``; else a BundleError that starts with ``who`` (the option
        or step that needs it, e.g. ``"--teacher runs/x/bundle"``) and says which kind it is and which was wanted."""
        if self.config.latent_source != source:
            raise BundleError(f"{who}: not a {ROLE[source]} bundle (latent_source {self.config.latent_source!r}, "
                              f"want {source!r})")
        return self

    @torch.no_grad()
    def act(self, obs: dict[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        """One observation (groups without a batch dim) -> (action_dim,) float32 action in [-1, 1]; ``correction``
        (Z,) is added to the latent first (a cautious start's shift: :meth:`start_correction`)."""
        if correction is not None:
            batched = {k: np.asarray(obs[k])[None] for k in self.config.obs_groups}
            return self.act_batch(batched, np.asarray(correction, np.float32).reshape(1, -1))[0]
        net = self.net if self.single is None else self.single
        return net(self._tensors(obs, batched=False)).numpy()[0]  # numpy's indexing keeps the interpreter's lock

    @torch.no_grad()
    def act_batch(self, obs: dict[str, Any], correction: np.ndarray | None = None) -> np.ndarray:
        """Observations with a leading N on every group -> (N, action_dim) float32 actions in [-1, 1];
        ``correction`` (N, Z) or (Z,) is added to the latent first."""
        tensors = self._tensors(obs, batched=True)
        if correction is None:
            return self.net(tensors).numpy()
        z = self.net.extractor.z(tensors) + torch.as_tensor(np.asarray(correction, np.float32))
        return self.net.mean(tensors, z).clamp(-1.0, 1.0).numpy()

    def start_correction(self, step: int) -> np.ndarray | None:
        """The (Z,) shift the latent gets at control step ``step`` of an episode (0 = its first action): the
        bundle's cautious start (``start_shift`` over its first ``start_steps`` steps), else None."""
        if step < self.config.start_steps:
            return np.asarray(self.config.start_shift, dtype=np.float32)
        return None

    @torch.no_grad()
    def latent(self, obs: dict[str, Any]) -> np.ndarray:
        """The latent z the actor would use: (Z,) for one observation, (N, Z) for a batch (leading N)."""
        key, shape = next(iter(self.config.obs_groups.items()))
        batched = np.ndim(obs[key]) == len(shape) + 1 if isinstance(obs, dict) and key in obs else False
        z = self.net.extractor.z(self._tensors(obs, batched=batched))
        return z.numpy() if batched else z[0].numpy()

    # ------------------------------------------------------------------ building
    @classmethod
    def from_sb3(cls, model: Any, *, control_hz: float = C.CONTROL_HZ, action_scale: float = C.ACTION_SCALE,
                 card: dict[str, Any] | None = None, sim: dict[str, Any] | None = None) -> PolicyBundle:
        """Bundle the acting path of a stable-baselines3 PPO (or its policy) built with our extractors.

        Copies the features extractor (normalization statistics included), ``mlp_extractor.policy_net`` and
        ``action_net``; the critic and the log-std are training-only and are left out. Pass the env's
        ``control_hz`` / ``action_scale`` when they differ from the defaults, and the ``sim`` it trained in
        (envs.sim_identity.sim_record).
        """
        policy = getattr(model, "policy", model)
        extractor = getattr(policy, "pi_features_extractor", None) or getattr(policy, "features_extractor", None)
        if isinstance(extractor, PrivilegedExtractor):
            source, kw = "privileged", dict(encoder=extractor.encoder.cfg)
        elif isinstance(extractor, StudentExtractor):
            source, kw = "adaptation", dict(adaptation=extractor.adaptation.cfg)
        else:
            raise BundleError("from_sb3 needs a policy whose features extractor is a PrivilegedExtractor or "
                              f"StudentExtractor (rotation.policy.features), got {type(extractor).__name__}")
        policy_net = policy.mlp_extractor.policy_net
        linears = [m for m in policy_net if isinstance(m, nn.Linear)]
        acts = {type(m) for m in policy_net if not isinstance(m, nn.Linear)}
        if acts != {nn.ELU} or len(policy_net) != 2 * len(linears):
            raise BundleError(f"from_sb3 expects an actor MLP of [Linear, ELU] layers (activation_fn=nn.ELU), "
                              f"got {policy_net}")
        config = BundleConfig(
            latent_source=source,  # type: ignore[arg-type]
            proprio_shape=extractor.proprio_shape,  # type: ignore[arg-type]
            actor_hidden=tuple(m.out_features for m in linears),
            action_dim=policy.action_net.out_features,
            norm_clip=extractor.proprio_norm.cfg.clip,
            control_hz=control_hz,
            action_scale=action_scale,
            card=dict(card or {}),
            sim=dict(sim or {}),
            **kw,  # type: ignore[arg-type]
        )
        net = ActorNet(config)
        skip = getattr(extractor, "bundle_skip", ())  # training-only parts (features.LatentMixExtractor)
        net.extractor.load_state_dict({k: v for k, v in extractor.state_dict().items() if not k.startswith(skip)})
        net.actor.load_state_dict(policy_net.state_dict())
        net.action_mean.load_state_dict(policy.action_net.state_dict())
        return cls(config, net.cpu().float())

    def to_student(self, adaptation: AdaptationConfig | None = None, card: dict[str, Any] | None = None
                   ) -> PolicyBundle:
        """A student bundle from this teacher: same actor and proprio normalization, fresh adaptation module."""
        self.require("privileged", "to_student")
        adaptation = adaptation or AdaptationConfig(latent_dim=self.config.latent_dim)
        config = replace(self.config, latent_source="adaptation", encoder=None, adaptation=adaptation, obs_groups={},
                         card=dict(card if card is not None else self.config.card))
        net = ActorNet(config)
        teacher = self.net.extractor
        assert isinstance(teacher, PrivilegedExtractor)
        net.extractor = StudentExtractor.from_teacher(teacher, config.observation_space(), adaptation)
        net.actor.load_state_dict(self.net.actor.state_dict())
        net.action_mean.load_state_dict(self.net.action_mean.state_dict())
        return PolicyBundle(config, net)

    def with_teacher_latent(self, teacher: PolicyBundle, card: dict[str, Any] | None = None) -> PolicyBundle:
        """This student's actor acting on ``teacher``'s privileged latent z (its env-factor encoder over ``priv``).

        The oracle-latent student: a latent correction such as the tactile adapter can at best make the student
        act like this, so its evaluation bounds what any correction of this student's latent can gain.
        """
        self.require("adaptation", "with_teacher_latent")
        teacher.require("privileged", "with_teacher_latent")
        for name in ("proprio_shape", "latent_dim", "action_dim", "control_hz", "action_scale", "sim"):
            mine, theirs = getattr(self.config, name), getattr(teacher.config, name)
            if to_jsonable(mine) != to_jsonable(theirs):
                raise BundleError(f"the student and the teacher disagree on {name}: {mine} vs {theirs}")
        config = replace(teacher.config, actor_hidden=self.config.actor_hidden, norm_clip=self.config.norm_clip,
                         card=dict(card or {}))
        net = ActorNet(config)
        net.extractor.load_state_dict(teacher.net.extractor.state_dict())
        net.extractor.proprio_norm.load_state_dict(self.net.extractor.proprio_norm.state_dict())
        net.actor.load_state_dict(self.net.actor.state_dict())
        net.action_mean.load_state_dict(self.net.action_mean.state_dict())
        return PolicyBundle(config, net)

    # ------------------------------------------------------------------ files
    def save(self, path: str | Path) -> Path:
        """Write ``path/config.json`` and ``path/model.safetensors``; returns the directory."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        tensors = {k: v.detach().cpu().contiguous() for k, v in self.net.state_dict().items()}
        _check_finite(tensors, path / WEIGHTS_FILE)
        save_file(tensors, str(path / WEIGHTS_FILE), metadata={"format_version": str(FORMAT_VERSION),
                                                                 "env_version": self.config.env_version})
        (path / CONFIG_FILE).write_text(json.dumps(to_jsonable(self.config), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> PolicyBundle:
        """Load a bundle directory, checking versions, shapes and that every weight is finite."""
        path = Path(path)
        cfg_file, weights_file = path / CONFIG_FILE, path / WEIGHTS_FILE
        for f in (cfg_file, weights_file):
            if not f.is_file():
                raise BundleError(f"bundle {path} is missing {f.name} (a bundle is a directory with {CONFIG_FILE} "
                                  f"and {WEIGHTS_FILE})")
        try:
            raw = json.loads(cfg_file.read_text())
        except json.JSONDecodeError as err:
            raise BundleError(f"{cfg_file} is not valid JSON: {err}") from err
        if not isinstance(raw, dict):
            raise BundleError(f"{cfg_file} must hold a JSON object, got {type(raw).__name__}")
        version = raw.get("format_version")
        if version != FORMAT_VERSION:
            raise BundleError(f"{cfg_file}: bundle format version {version!r}, but this code reads format version "
                              f"{FORMAT_VERSION}; re-export the bundle with a matching version of the package")
        env_version = raw.get("env_version")
        if env_version != ENV_VERSION:
            raise BundleError(f"{cfg_file}: bundle was trained for env {env_version!r}, expected {ENV_VERSION!r}")
        try:
            config = from_jsonable(BundleConfig, raw)
        except (TypeError, ValueError) as err:
            raise BundleError(f"{cfg_file}: invalid bundle config: {err}") from err
        try:
            tensors = load_file(str(weights_file))
        except (SafetensorError, OSError) as err:
            raise BundleError(f"{weights_file} is not a readable safetensors file: {err}") from err
        try:
            net = ActorNet(config)
        except (ValueError, RuntimeError) as err:  # e.g. convolutions longer than the history they read
            raise BundleError(f"{cfg_file}: the networks it describes cannot be built: {err}") from err
        expected = net.state_dict()
        missing = sorted(set(expected) - set(tensors))
        unexpected = sorted(set(tensors) - set(expected))
        if missing or unexpected:
            raise BundleError(f"{weights_file} does not match {CONFIG_FILE}: missing tensors {missing}, "
                              f"unexpected tensors {unexpected}")
        for key, want in expected.items():
            if tuple(tensors[key].shape) != tuple(want.shape):
                raise BundleError(f"{weights_file}: tensor {key!r} has shape {tuple(tensors[key].shape)}, expected "
                                  f"{tuple(want.shape)} from {CONFIG_FILE} (observation/network sizes disagree)")
        _check_finite(tensors, weights_file)
        net.load_state_dict({k: v.to(expected[k].dtype) for k, v in tensors.items()})
        return cls(config, net)

    def __repr__(self) -> str:
        c = self.config
        return (f"PolicyBundle(latent_source={c.latent_source!r}, obs_groups={dict(c.obs_groups)}, "
                f"actor_hidden={c.actor_hidden}, control_hz={c.control_hz})")


def _check_finite(tensors: dict[str, torch.Tensor], where: Path) -> None:
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise BundleError(f"{where}: non-finite values (NaN or inf) in tensor(s) {bad}; every weight must be finite")


def shipped_bundles() -> list[str]:
    """Names of the bundles shipped inside the package (``rotation/policies/<name>/config.json``)."""
    if not SHIPPED_DIR.is_dir():
        return []
    return sorted(p.name for p in SHIPPED_DIR.iterdir() if (p / CONFIG_FILE).is_file())


def combined_correction(touch: np.ndarray | None, start: np.ndarray | None) -> np.ndarray | None:
    """The latent correction a control step acts with: a tactile adapter's ``touch`` correction ((N, Z), (1, Z) or
    (Z,)), a cautious start's ``start`` shift ((Z,), :meth:`PolicyBundle.start_correction`), their sum, or None
    (the policy as it is)."""
    if start is None:
        return touch
    if touch is None:
        return start
    return np.asarray(touch, np.float32) + start


def resolve_bundle(name_or_path: str | Path) -> Path:
    """A bundle directory from a path, or from the name of a shipped bundle (``teacher``, ``student``)."""
    path = Path(name_or_path)
    if path.is_dir():
        return path
    names = shipped_bundles()
    if str(name_or_path) in names:
        return SHIPPED_DIR / str(name_or_path)
    listing = ", ".join(names) if names else "none are shipped in this installation yet"
    raise BundleError(f"no bundle directory at {str(name_or_path)!r} and no shipped bundle of that name; "
                      f"shipped bundles: {listing}")


def load_policy_bundle(name_or_path: str | Path) -> PolicyBundle:
    """Load a plain (teacher or student) bundle by shipped name or directory path: what training reads. A tactile
    adapter or an ensemble is refused with what it is; rotation.bundles.load_bundle loads every kind."""
    path = resolve_bundle(name_or_path)
    kind = _kind(path)
    if kind is not None:
        raise BundleError(f"{path} holds a {kind!r} bundle, not a teacher or student bundle; give the bundle of "
                          "a plain policy here (an adapter names its student in its config.json)")
    return PolicyBundle.load(path)


def _kind(path: Path) -> str | None:
    """The ``kind`` field of a bundle's config.json: present in adapter and ensemble bundles, absent in plain ones."""
    try:
        raw = json.loads((path / CONFIG_FILE).read_text())
    except (OSError, ValueError):
        return None  # PolicyBundle.load says what is wrong with it
    kind = raw.get("kind") if isinstance(raw, dict) else None
    return kind if isinstance(kind, str) else None
