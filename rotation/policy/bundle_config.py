"""What a policy bundle's config.json says: format and env versions, the latent's source, network sizes,
observation groups, normalization, joint limits, action scale and control rate (BundleConfig), and the error
every bundle check raises.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from gymnasium import spaces

from envs import constants as C
from envs.errors import RequestRefused
from rotation.policy.bundle_checks import type_problems, value_problems
from rotation.policy.networks import AdaptationConfig, EnvFactorEncoderConfig

FORMAT_VERSION = 1
"""Version of the bundle layout written by this code; bump it when config.json or tensor names change meaning."""
ENV_VERSION = "RotateCup-v0"
"""The env (observation and action contract) the bundled policies act in."""
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"

LatentSource = Literal["privileged", "adaptation"]
LATENT_GROUP: dict[str, str] = {"privileged": "priv", "adaptation": "proprio_hist"}
"""Observation group the latent is computed from, per latent source."""
ROLE: dict[str, str] = {"privileged": "teacher", "adaptation": "student"}
"""What a bundle of each latent source is called in messages."""


class BundleError(ValueError):
    """A bundle that cannot be loaded or used: says what is wrong and what was expected."""


class BundleRefused(BundleError, RequestRefused):
    """A bundle that reads fine but cannot be used as asked: it names a student or an encoder that is missing, or
    whose weights changed since it was trained (`rotate` exits with status 1, not 2)."""


@dataclass(frozen=True)
class BundleConfig:
    """Everything needed to rebuild a policy and act with it (saved as config.json beside the weights)."""

    latent_source: LatentSource = "privileged"
    """Where z comes from: 'privileged' (env-factor encoder over `priv`, the teacher) or 'adaptation' (temporal-conv
    module over `proprio_hist`, the student)."""
    obs_groups: dict[str, tuple[int, ...]] = field(default_factory=dict)
    """Observation groups the policy reads and their shapes without the batch dim; derived from the networks when
    left empty."""
    encoder: EnvFactorEncoderConfig | None = None
    """Env-factor encoder sizes (latent_source 'privileged')."""
    adaptation: AdaptationConfig | None = None
    """Adaptation module sizes (latent_source 'adaptation')."""
    proprio_shape: tuple[int, int] = (C.PROPRIO_STEPS, C.PROPRIO_DIM)
    """Shape of the `proprio` group the actor reads (steps, features)."""
    actor_hidden: tuple[int, ...] = (512, 256, 128)
    """Hidden widths of the actor MLP (ELU after each), followed by a linear layer to the action mean."""
    action_dim: int = C.NUM_JOINTS
    """Number of actions (one relative joint-target step per joint, Allegro bus order)."""
    norm_clip: float = 5.0
    """Clip of the normalized observations (the statistics themselves are tensors in model.safetensors)."""
    control_hz: float = C.CONTROL_HZ
    """Rate (Hz) the policy was trained to act at."""
    action_scale: float = C.ACTION_SCALE
    """Joint-target change per unit action (rad): target += action_scale * action."""
    joint_lower: tuple[float, ...] = tuple(C.JOINT_LOWER.tolist())
    """Joint-target lower limits (rad, bus order) the env clamps to."""
    joint_upper: tuple[float, ...] = tuple(C.JOINT_UPPER.tolist())
    """Joint-target upper limits (rad, bus order) the env clamps to."""
    adapter: str | None = None
    """Optional reference to a tactile adapter (a path or shipped name) that corrects this policy's latent."""
    touch_encoder: str | None = None
    """Optional reference to the frozen touch encoder the adapter reads."""
    start_shift: tuple[float, ...] = ()
    """A cautious start: added to the latent z over the first ``start_steps`` control steps of each episode (of each
    deploy run), then nothing; (latent_dim,) values, empty with ``start_steps`` 0 (scripts/cautious_start.py)."""
    start_steps: int = 0
    """How many control steps from an episode's first the ``start_shift`` is added for (0: never)."""
    card: dict[str, Any] = field(default_factory=dict)
    """Free-form metadata: how it was trained, the env config, steps, scores."""
    sim: dict[str, Any] = field(default_factory=dict)
    """The simulation it trained in (envs.sim_identity.sim_record): the hand variant, a fingerprint of that hand's
    kinematics and fingertips, the contact settings and torque limits. Empty in a bundle from before bundles
    recorded it: such a policy trained on the 'digit360' hand. Jobs refuse a policy on another hand."""
    format_version: int = FORMAT_VERSION
    """Bundle layout version (see FORMAT_VERSION)."""
    env_version: str = ENV_VERSION
    """Env the policy acts in (see ENV_VERSION)."""

    def __post_init__(self) -> None:
        # types first: a string where a number belongs must not surface later as a TypeError (or, on a hand, after
        # the motors are on); then the ranges (rotation.policy.bundle_checks says which and why)
        problems = type_problems(self)
        if problems:
            raise BundleError("; ".join(problems))
        if self.latent_source not in LATENT_GROUP:
            raise BundleError(f"latent_source must be one of {sorted(LATENT_GROUP)}, got {self.latent_source!r}")
        # defaults for the latent network, then the observation groups implied by the networks
        if self.latent_source == "privileged" and self.encoder is None:
            object.__setattr__(self, "encoder", EnvFactorEncoderConfig())
        if self.latent_source == "adaptation" and self.adaptation is None:
            object.__setattr__(self, "adaptation", AdaptationConfig())
        problems = value_problems(self)
        if problems:
            raise BundleError("; ".join(problems))
        expected = self.expected_groups()
        groups = {k: tuple(int(d) for d in v) for k, v in self.obs_groups.items()} or expected
        if groups != expected:
            raise BundleError(f"obs_groups {groups} do not match the networks' inputs {expected} "
                              f"(latent_source {self.latent_source!r})")
        object.__setattr__(self, "obs_groups", groups)

    @property
    def latent_dim(self) -> int:
        net = self.encoder if self.latent_source == "privileged" else self.adaptation
        assert net is not None
        return net.latent_dim

    def expected_groups(self) -> dict[str, tuple[int, ...]]:
        """Observation groups (name -> shape) the networks described here read."""
        groups: dict[str, tuple[int, ...]] = {"proprio": tuple(self.proprio_shape)}
        if self.latent_source == "privileged":
            assert self.encoder is not None
            groups["priv"] = (self.encoder.in_dim,)
        else:
            assert self.adaptation is not None
            groups["proprio_hist"] = (self.adaptation.steps, self.adaptation.in_dim)
        return groups

    def observation_space(self) -> spaces.Dict:
        return spaces.Dict({k: spaces.Box(-np.inf, np.inf, s, np.float32) for k, s in self.obs_groups.items()})

    def zero_observation(self) -> dict[str, np.ndarray]:
        """An observation of zeros in every group the policy reads (warm-ups and tracing)."""
        return {k: np.zeros(shape, dtype=np.float32) for k, shape in self.obs_groups.items()}
