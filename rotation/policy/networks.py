"""Networks of the Hora-style teacher and student (docs/reference/hora.md, "Networks").

nanoGPT style: one config dataclass per model, small modules, a shape comment on every reshape. Shapes use
B = batch, T = history steps, D = per-step proprioception (32), Z = latent size (8).

- :class:`RunningNorm`: running mean/std observation normalization kept in buffers, so the statistics travel with
  the weights (safetensors, ONNX) and nothing outside the network re-declares them.
- :class:`EnvFactorEncoder` (mu): privileged vector (9) -> latent z in (-1, 1)^8.
- :class:`AdaptationModule` (phi): 30 steps of proprioception (30, 32) -> an estimate of z.
- :func:`mlp`: the Linear/activation stack used for all of them and for the actor/critic heads.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from envs.constants import HISTORY_STEPS, PRIV_DIM, PROPRIO_DIM
from envs.validation import check_int, check_types


def mlp(sizes: Sequence[int], activation: type[nn.Module] = nn.ELU, activate_last: bool = False) -> nn.Sequential:
    """Linear layers ``sizes[0] -> sizes[1] -> ... -> sizes[-1]`` with ``activation`` between them.

    With ``activate_last`` the activation also follows the last layer; this gives exactly the module layout of
    stable-baselines3's ``mlp_extractor.policy_net`` (``[Linear, act] * n``), so its weights load by index.
    """
    if len(sizes) < 2:
        raise ValueError(f"mlp needs at least an input and an output size, got {list(sizes)}")
    layers: list[nn.Module] = []
    for i, (d_in, d_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nn.Linear(d_in, d_out))
        if activate_last or i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


# --------------------------------------------------------------------------------------------------------------------
# Observation normalization


@dataclass(frozen=True)
class RunningNormConfig:
    """Running mean/std normalization of one observation group."""

    shape: tuple[int, ...] = (PROPRIO_DIM,)
    """Trailing feature shape the statistics are kept for; all leading dims (batch, history steps) are pooled."""
    eps: float = 1e-5
    """Added to the variance before the square root."""
    clip: float = 5.0
    """Normalized values are clipped to [-clip, clip] (rl_games' default, which Hora trained with)."""


class RunningNorm(nn.Module):
    """``(x - mean) / sqrt(var + eps)`` clipped, with statistics updated from every batch seen in training mode.

    Statistics are buffers (``mean``, ``var``: ``shape``; ``count``: scalar, float64 so it stays exact past 2^24
    samples), so ``state_dict`` / safetensors / ONNX export carry them. In ``eval()`` mode the statistics are frozen;
    that is how a trained teacher and every deployed policy use it. Updates use the parallel (Chan et al.) merge of
    batch moments into the running moments, the same as rl_games' ``RunningMeanStd``.
    """

    def __init__(self, cfg: RunningNormConfig = RunningNormConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.register_buffer("mean", torch.zeros(cfg.shape))
        self.register_buffer("var", torch.ones(cfg.shape))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    frozen: bool = False
    """Set True to keep the statistics fixed even in training mode (e.g. while only a critic trains)."""

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge the moments of ``x`` (..., *shape) into the running statistics."""
        nd = len(self.cfg.shape)
        if tuple(x.shape[x.dim() - nd:]) != self.cfg.shape:
            raise ValueError(f"RunningNorm: expected trailing shape {self.cfg.shape}, got {tuple(x.shape)}")
        flat = x.detach().reshape(-1, *self.cfg.shape).double()  # (M, *shape), every leading dim pooled
        n = flat.shape[0]
        if n == 0:
            return
        b_mean = flat.mean(0)
        b_var = flat.var(0, unbiased=False)
        mean, var, count = self.mean.double(), self.var.double(), self.count
        total = count + n
        delta = b_mean - mean
        new_mean = mean + delta * (n / total)
        m2 = var * count + b_var * n + delta.square() * (count * n / total)
        self.mean.copy_(new_mean.float())
        self.var.copy_((m2 / total).float())
        self.count.copy_(total)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., *shape) -> normalized (..., *shape); updates the statistics first when training."""
        if self.training and not self.frozen:
            self.update(x)
        y = (x - self.mean) / torch.sqrt(self.var + self.cfg.eps)
        return y.clamp(-self.cfg.clip, self.cfg.clip)


# --------------------------------------------------------------------------------------------------------------------
# Env-factor encoder (teacher)


@dataclass(frozen=True)
class EnvFactorEncoderConfig:
    """Hora's env-factor encoder mu: privileged info -> latent z."""

    in_dim: int = PRIV_DIM
    """Size of the privileged vector (envs.constants.PRIV_FIELDS)."""
    hidden: tuple[int, ...] = (256, 128)
    """Hidden layer widths (Hora: 256, 128)."""
    latent_dim: int = 8
    """Size of z (Hora: 8)."""


class EnvFactorEncoder(nn.Module):
    """(B, 9) raw privileged vector -> (B, 8) latent in (-1, 1), MLP with ELU then tanh.

    The privileged vector is fed raw, as Hora does since v0.0.2 (docs/reference/hora.md). Hora's MLP class also puts an
    ELU after the last layer before the tanh (z in (-0.63, 1)); here the last layer is linear, so z spans (-1, 1),
    the same range the adaptation module's tanh output covers.
    """

    def __init__(self, cfg: EnvFactorEncoderConfig = EnvFactorEncoderConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.mlp = mlp([cfg.in_dim, *cfg.hidden, cfg.latent_dim], nn.ELU)

    def forward(self, priv: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.mlp(priv))  # (B, Z)


# --------------------------------------------------------------------------------------------------------------------
# Adaptation module (student)


@dataclass(frozen=True)
class AdaptationConfig:
    """Hora's temporal-convolution adaptation module phi: proprioceptive history -> estimate of z."""

    in_dim: int = PROPRIO_DIM
    """Per-step proprioception size D (16 scaled joint positions + 16 targets)."""
    steps: int = HISTORY_STEPS
    """History length T (Hora: 30 policy steps = 1.5 s at 20 Hz)."""
    embed_dim: int = 32
    """Width of the per-step Linear-ReLU-Linear-ReLU embedding."""
    channels: int = 32
    """Channels of every temporal convolution."""
    kernels: tuple[int, ...] = (9, 5, 5)
    """Kernel size of each Conv1d (Hora: 9, 5, 5)."""
    strides: tuple[int, ...] = (2, 1, 1)
    """Stride of each Conv1d (Hora: 2, 1, 1); with T = 30 the lengths go 30 -> 11 -> 7 -> 3."""
    latent_dim: int = 8
    """Size of the estimated z (must match the teacher's EnvFactorEncoderConfig.latent_dim)."""

    def __post_init__(self) -> None:
        check_types(self, "adaptation.")
        for name in ("in_dim", "steps", "embed_dim", "channels"):
            check_int(f"adaptation.{name}", getattr(self, name), 1, 4096)
        check_int("adaptation.latent_dim", self.latent_dim, 1, 1024)
        if not self.kernels or len(self.kernels) != len(self.strides):
            raise ValueError(f"adaptation.kernels and adaptation.strides must list one value per convolution (at "
                             f"least one), got {len(self.kernels)} kernels and {len(self.strides)} strides")
        for name in ("kernels", "strides"):
            if not all(1 <= v <= self.steps for v in getattr(self, name)):
                raise ValueError(f"adaptation.{name} must be integers in [1, {self.steps}], got "
                                 f"{getattr(self, name)!r}")
        # that the history outlasts all the convolutions together is checked when the module is built (conv_lengths)

    def conv_lengths(self) -> list[int]:
        """Sequence length after each convolution, starting with ``steps``."""
        if len(self.kernels) != len(self.strides):
            raise ValueError(f"AdaptationConfig: {len(self.kernels)} kernels but {len(self.strides)} strides")
        lengths = [self.steps]
        for k, s in zip(self.kernels, self.strides, strict=True):
            lengths.append((lengths[-1] - k) // s + 1)
        if lengths[-1] < 1:
            raise ValueError(f"AdaptationConfig: history of {self.steps} steps is too short for kernels "
                             f"{self.kernels} / strides {self.strides} (lengths {lengths})")
        return lengths


class AdaptationModule(nn.Module):
    """(B, 30, 32) proprioceptive history -> (B, 8) latent estimate in (-1, 1) (Hora's ``adapt_tconv``)."""

    def __init__(self, cfg: AdaptationConfig = AdaptationConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        lengths = cfg.conv_lengths()
        self.embed = nn.Sequential(
            nn.Linear(cfg.in_dim, cfg.embed_dim), nn.ReLU(), nn.Linear(cfg.embed_dim, cfg.embed_dim), nn.ReLU()
        )
        convs: list[nn.Module] = []
        c_in = cfg.embed_dim
        for k, s in zip(cfg.kernels, cfg.strides, strict=True):
            convs += [nn.Conv1d(c_in, cfg.channels, kernel_size=k, stride=s), nn.ReLU()]
            c_in = cfg.channels
        self.temporal = nn.Sequential(*convs)
        self.proj = nn.Linear(cfg.channels * lengths[-1], cfg.latent_dim)

    def forward(self, hist: torch.Tensor) -> torch.Tensor:
        x = self.embed(hist)  # (B, T, E)
        x = x.transpose(1, 2)  # (B, E, T): Conv1d wants channels first
        x = self.temporal(x)  # (B, C, 3)
        x = x.flatten(1)  # (B, C * 3) = (B, 96), channel-major
        return torch.tanh(self.proj(x))  # (B, Z)
