"""The tactile adapter network: frozen touch tokens -> a correction of the student's latent.

    z_hat = phi(history) + ZeroLinear(g(pooled fingertip tokens, phi(history) [, joint tracking]))

``g`` pools each sensor sample's tokens (one Digit 360 fingertip for Sparsh-X, the whole hand for Sparsh-skin)
with one attentive pooler shared by the samples (rotation.tactile.models.pooling, over ``TokenInterface.concat``: every
token group layer-normed, so any encoder and any modality subset plug in unchanged), adds a learned per-sample
embedding (which finger), concatenates the samples and, optionally, the student's own latent and the joints' tracking
over the proprioceptive history (:func:`tracking_features`), and runs a small MLP.
``ZeroLinear`` is a linear layer whose weight and bias start at exactly zero (ControlNet's "zero convolution"):
at initialization the correction is exactly 0.0, so the adapted policy acts bit for bit like its student, and
training can only move it away from there as far as the latent error pays for.

Shapes (B = batch, S = sensor samples per step, e.g. 4 fingertips, N = tokens, D = encoder width, Z = latent)::

    tokens  {sample: {group: (B, N_g, D)}}   -> pooled (B, S, D) -> g (B, H) -> ZeroLinear -> (B, Z)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from envs.constants import JOINT_LOWER, JOINT_UPPER, NUM_JOINTS
from rotation.policy.networks import mlp
from rotation.tactile.models.pooling import AttentivePooler
from rotation.tactile.models.tokens import TokenInterface

TRACKING_DIM = 3 * NUM_JOINTS
"""Width of :func:`tracking_features`: per joint, the mean and the standard deviation of its tracking error and its
mean position."""


def tracking_features(hist: Tensor) -> Tensor:
    """(B, T, 32) proprioceptive history (per step 16 joint positions scaled to [-1, 1] by the joint limits, then the
    16 joint targets in rad; the env's ``proprio_hist``) -> (B, 48): per joint over the T steps, the mean and the
    standard deviation of the tracking error (target - position, rad), then the mean position (rad).

    On the palm-up hand the palm and the phalanges carry the cup (experiments/tools/load_share.py), and the
    position-controlled joints under them sag by what they carry: these features say how heavy a cup is far better
    than the student's phi does (docs/adapter.md), and a real hand measures them as the simulator does."""
    if hist.ndim != 3 or hist.shape[-1] != 2 * NUM_JOINTS:
        raise ValueError(f"tracking_features: expected a (batch, steps, {2 * NUM_JOINTS}) history, got "
                         f"{tuple(hist.shape)}")
    lower = torch.as_tensor(JOINT_LOWER, dtype=hist.dtype)
    span = torch.as_tensor(JOINT_UPPER - JOINT_LOWER, dtype=hist.dtype)
    q = lower + (hist[..., :NUM_JOINTS] + 1.0) * 0.5 * span  # rad (envs.constants.unscale_joints)
    err = hist[..., NUM_JOINTS:] - q
    return torch.cat([err.mean(1), err.std(1, unbiased=False), q.mean(1)], dim=-1)


@dataclass(frozen=True)
class AdapterNetConfig:
    """Sizes of the adapter network (saved in the adapter bundle's config.json)."""

    samples: tuple[str, ...]
    """Sensor samples per step, in order (Sparsh-X: the fingertips, e.g. index, middle, ring, thumb)."""
    groups: tuple[tuple[str, int], ...]
    """The encoder's token groups it reads, (name, count) in the encoder's order (its TokenInterface)."""
    width: int
    """Token width D of the encoder."""
    latent_dim: int = 8
    """Size of the student's latent z that the adapter corrects."""
    hidden: tuple[int, ...] = (256, 128)
    """Hidden widths of g's MLP (ELU after each)."""
    pool_heads: int = 4
    """Attention heads of the pooler (the width must be a multiple)."""
    with_latent: bool = True
    """Also feed g the student's own latent phi(history) (proprioceptive features)."""
    tracking: bool = False
    """Also feed g the joints' tracking over the proprioceptive history (:func:`tracking_features`, normalized by
    statistics measured on the student's rollouts before training and kept with the weights)."""
    touch: bool = True
    """Read the touch tokens. False blanks them: g sees each sample's embedding alone (the same for every input),
    so the adapter learns from the student's latent and, with ``tracking``, the joints' tracking: the ablation that
    says what touch adds (finetune-adapter --blind-touch)."""

    def __post_init__(self) -> None:
        if not self.samples or len(set(self.samples)) != len(self.samples):
            raise ValueError(f"adapter: samples must be distinct names, got {self.samples}")
        if self.width < 1 or self.width % self.pool_heads:
            raise ValueError(f"adapter: width {self.width} must be a positive multiple of pool_heads "
                             f"{self.pool_heads}")
        if self.latent_dim < 1 or not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"adapter: latent_dim {self.latent_dim} and hidden {self.hidden} must be positive")
        TokenInterface(tuple((str(n), int(c)) for n, c in self.groups), self.width)  # validates the groups

    @property
    def interface(self) -> TokenInterface:
        return TokenInterface(tuple((str(n), int(c)) for n, c in self.groups), self.width)


class ZeroLinear(nn.Linear):
    """A linear layer that starts as the zero map: weight and bias exactly 0.0 (ControlNet's zero convolution)."""

    def reset_parameters(self) -> None:
        nn.init.zeros_(self.weight)
        if self.bias is not None:
            nn.init.zeros_(self.bias)


class TouchAdapter(nn.Module):
    """g + ZeroLinear: ``forward(tokens, z_student) -> (B, Z)`` correction added to the student's latent."""

    def __init__(self, cfg: AdapterNetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.interface = cfg.interface
        s, d = len(cfg.samples), cfg.width
        self.pool = AttentivePooler(d, cfg.pool_heads)
        self.sample_embed = nn.Parameter(torch.zeros(s, d))
        nn.init.trunc_normal_(self.sample_embed, std=0.02)
        extra = (cfg.latent_dim if cfg.with_latent else 0) + (TRACKING_DIM if cfg.tracking else 0)
        self.g = mlp([s * d + extra, *cfg.hidden], nn.ELU, activate_last=True)
        self.zero = ZeroLinear(cfg.hidden[-1], cfg.latent_dim)
        if cfg.tracking:  # what the features are normalized by: set_tracking_norm, then saved with the weights
            self.register_buffer("track_mean", torch.zeros(TRACKING_DIM))
            self.register_buffer("track_std", torch.ones(TRACKING_DIM))

    @property
    def tracking_dim(self) -> int:
        """Width of the tracking features it reads (0 when it reads none)."""
        return TRACKING_DIM if self.cfg.tracking else 0

    def set_tracking_norm(self, mean: Tensor, std: Tensor) -> None:
        """Normalize the tracking features by this mean and standard deviation (each (48,); std floored at 1e-4)."""
        if not self.cfg.tracking:
            raise ValueError("adapter: this adapter reads no joint tracking")
        mean, std = torch.as_tensor(mean, dtype=torch.float32), torch.as_tensor(std, dtype=torch.float32)
        if mean.shape != (TRACKING_DIM,) or std.shape != (TRACKING_DIM,):
            raise ValueError(f"adapter: tracking statistics must be ({TRACKING_DIM},), got {tuple(mean.shape)} and "
                             f"{tuple(std.shape)}")
        if not (torch.isfinite(mean).all() and torch.isfinite(std).all()):
            raise ValueError("adapter: non-finite tracking statistics")
        self.track_mean.copy_(mean)
        self.track_std.copy_(std.clamp_min(1e-4))

    def pooled(self, tokens: dict[str, dict[str, Tensor]]) -> Tensor:
        """{sample: {group: (B, N_g, D)}} -> (B, S, D): one attentive pooling per sample, plus its embedding."""
        missing = [s for s in self.cfg.samples if s not in tokens]
        if missing:
            raise ValueError(f"adapter: no tokens for {missing} (it reads {list(self.cfg.samples)})")
        parts = [self.interface.concat({g: tokens[s][g] for g in self.interface.names}) for s in self.cfg.samples]
        b = parts[0].shape[0]
        flat = torch.cat(parts, dim=0)  # (S * B, N, D): one pooler call for every sample
        pooled = self.pool(flat).view(len(parts), b, -1).transpose(0, 1)  # (B, S, D)
        return pooled + self.sample_embed.to(pooled.dtype)

    def hidden(self, pooled: Tensor, z_student: Tensor, track: Tensor | None = None) -> Tensor:
        """(B, S, D) pooled features, the student's (B, Z) latent and, for an adapter that reads them, the (B, 48)
        tracking features (:func:`tracking_features`; ignored otherwise) -> (B, H) g's output, the zero layer's
        input."""
        if not self.cfg.touch:  # blind: the samples' embeddings alone, whatever the tokens were
            pooled = self.sample_embed.to(pooled.dtype).expand(pooled.shape)
        x = pooled.flatten(1)  # (B, S * D)
        if self.cfg.with_latent:
            x = torch.cat([x, z_student.to(x.dtype)], dim=-1)
        if self.cfg.tracking:
            if track is None or track.shape != (x.shape[0], TRACKING_DIM):
                got = None if track is None else tuple(track.shape)
                raise ValueError(f"adapter: it reads the joint tracking, ({x.shape[0]}, {TRACKING_DIM}) features; "
                                 f"got {got}")
            x = torch.cat([x, ((track - self.track_mean) / self.track_std).to(x.dtype)], dim=-1)
        return self.g(x)

    def from_pooled(self, pooled: Tensor, z_student: Tensor, track: Tensor | None = None) -> Tensor:
        """(B, S, D) pooled features, the student's (B, Z) latent [and (B, 48) tracking] -> (B, Z) correction."""
        return self.zero(self.hidden(pooled, z_student, track))

    def forward(self, tokens: dict[str, dict[str, Tensor]], z_student: Tensor, track: Tensor | None = None
                ) -> Tensor:
        return self.from_pooled(self.pooled(tokens), z_student, track)
