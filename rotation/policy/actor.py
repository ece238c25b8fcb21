"""The acting network of a bundle: normalized proprioception and the latent z through the actor MLP to the
action mean (ActorNet), the same with a correction added to z (CorrectedActor, for the tactile adapter), and
tracing a module once for the real-time loop.
"""

from __future__ import annotations

import warnings

import torch
from torch import nn

from rotation.policy.bundle_config import BundleConfig
from rotation.policy.features import LatentExtractor, PrivilegedExtractor, StudentExtractor
from rotation.policy.networks import mlp


class ActorNet(nn.Module):
    """The acting path: (B, ...) observation groups -> (B, action_dim) deterministic action in [-1, 1]."""

    def __init__(self, cfg: BundleConfig) -> None:
        super().__init__()
        space = cfg.observation_space()
        self.extractor: LatentExtractor
        if cfg.latent_source == "privileged":
            self.extractor = PrivilegedExtractor(space, cfg.encoder, norm_clip=cfg.norm_clip)
        else:
            self.extractor = StudentExtractor(space, cfg.adaptation, norm_clip=cfg.norm_clip)
        # [Linear, ELU] * n: the layout of SB3's mlp_extractor.policy_net, so its weights load by index
        self.actor = mlp([self.extractor.features_dim, *cfg.actor_hidden], nn.ELU, activate_last=True)
        self.action_mean = nn.Linear(cfg.actor_hidden[-1], cfg.action_dim)

    def mean(self, obs: dict[str, torch.Tensor], z: torch.Tensor | None = None) -> torch.Tensor:
        """Unclipped action mean (B, A); a given ``z`` replaces the extractor's latent (DAgger, adapters)."""
        if z is None:
            return self.action_mean(self.actor(self.extractor(obs)))  # features (B, 96 + Z)
        return self.head(self.proprio_features(obs), z)

    def proprio_features(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, S * D) normalized proprioception: the part of the actor's input that is not the latent."""
        return self.extractor.proprio_norm(obs["proprio"]).flatten(1)

    def head(self, proprio: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Unclipped action mean (B, A) from :meth:`proprio_features` and a latent (B, Z) (differentiable in z: an
        adapter's action-matching loss)."""
        return self.action_mean(self.actor(torch.cat([proprio, z], dim=-1)))

    def forward(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.mean(obs).clamp(-1.0, 1.0)


class CorrectedActor(nn.Module):
    """``net``'s clipped action with its latent moved by ``correction`` (B, Z): the acting path of a student with a
    tactile adapter's correction (adapters.bundle.AdaptedPolicy)."""

    def __init__(self, net: ActorNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, obs: dict[str, torch.Tensor], correction: torch.Tensor) -> torch.Tensor:
        return self.net.mean(obs, self.net.extractor.z(obs) + correction).clamp(-1.0, 1.0)


WARM_UP_CALLS = 3
"""Calls of a freshly traced module before it is used (TorchScript optimizes it during the first two)."""


def trace_single(module: nn.Module, example: tuple) -> nn.Module:
    """``module`` traced with TorchScript for inputs shaped like ``example`` (one observation).

    A traced network runs its whole forward in one call that does not hold Python's interpreter lock, where the
    eager network takes the lock back after each of its few dozen operations. In deploy the policy's thread shares
    the lock with the hand's and the sensors' threads (and with emulated hardware), and the eager forward waited
    its turn so often that it missed its 30 ms budget on a busy 2-core machine. Same operations, same results
    (checked in tests/policy/test_bundle.py). TorchScript profiles and optimizes a traced module in its first calls,
    which are slow: they are made here, on ``example``."""
    with torch.no_grad(), warnings.catch_warnings():
        # torch 2.9+ calls jit.trace deprecated (torch.compile needs a C++ toolchain at run time); input checks in
        # forward become constants of the trace (TracerWarning): the callers check their inputs before the trace
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        try:
            traced = torch.jit.trace(module.eval(), example, strict=False, check_trace=False)
        except (AttributeError, RuntimeError) as err:  # a torch without TorchScript: the eager module still works
            warnings.warn(f"TorchScript tracing failed ({err}); acting with the eager network", stacklevel=2)
            return module
        for _ in range(WARM_UP_CALLS):
            traced(*example)
    return traced
