"""The Sparsh-skin decoders of `rotate probe --encoder skin` (docs/reference/sparsh.md "Sparsh-skin", "Decoders"):

- ``force`` (instantaneous): the attentive pooler + MLP over one window's 368 tokens -> the force on each of the
  18 pads (``labels/skin_force``, N, the label's three components), smooth-L1 on standardized targets; RMSE per
  axis over pads and windows.
- ``pose`` (temporal): S consecutive 0.1 s windows, each pooled to one vector, + a sinusoidal embedding of the
  window's place in the sequence -> one causal transformer block -> at every window the object's pose relative to
  the sequence's first window: position change (m, world frame) and rotation vector of q_0^-1 q_t (rad, in the
  object's frame at the start); RMSE of the position and rotation errors.
- ``joystick`` (temporal, the same head): the joystick's roll, pitch, yaw (``labels/joystick``, rad); RMSE each.

Temporal samples come from rotation.data.skin.SkinWindows with ``sequence=S``; labels are (S, ...) per sample
and every window of a sequence is a causal prediction (it sees only the windows up to its own).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from rotation.tactile.models.blocks import Block
from rotation.tactile.models.pooling import AttentivePooler
from rotation.tactile.models.posembed import frequency_bands, sincos_embedding


def _rmse(pred: np.ndarray, target: np.ndarray) -> float:
    return float(np.sqrt(np.mean((pred - target) ** 2)))


def _rmse_norm(pred: np.ndarray, target: np.ndarray) -> float:
    """RMSE of the error vectors' length: sqrt(mean |p - t|^2) over the rows."""
    return float(np.sqrt(np.mean(np.sum((pred - target) ** 2, axis=-1))))


# ------------------------------------------------------------------------------------------------ targets
def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of quaternions (..., 4), w first."""
    w1, x1, y1, z1 = a.unbind(-1)
    w2, x2, y2, z2 = b.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], dim=-1)


def quat_conj(q: Tensor) -> Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def rotation_vector(q: Tensor) -> Tensor:
    """Quaternions (..., 4) wxyz -> rotation vectors (..., 3) (axis x angle, angle in [0, pi])."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q = torch.where(q[..., :1] < 0, -q, q)  # q and -q are one rotation: take w >= 0
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)  # sin(angle / 2)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    scale = torch.where(s > 1e-8, angle / s.clamp_min(1e-8), torch.full_like(s, 2.0))  # angle / sin(angle/2) -> 2
    return v * scale


def relative_pose(pose: Tensor) -> Tensor:
    """Object poses (B, S, 7) [position m, quaternion wxyz] -> (B, S, 6) pose relative to the first of each
    sequence: [p_t - p_0 (world frame), rotation vector of q_0^-1 q_t]."""
    p, q = pose[..., :3], pose[..., 3:7]
    dq = quat_mul(quat_conj(q[:, :1]).expand_as(q), q)
    return torch.cat([p - p[:, :1], rotation_vector(dq)], dim=-1)


def force_metrics(pred: np.ndarray, target: np.ndarray) -> dict[str, float]:
    """(N, 54) pad forces -> RMSE of each component over pads and windows (N)."""
    p, t = pred.reshape(-1, 3), target.reshape(-1, 3)
    return {f"rmse_{axis}_N": _rmse(p[:, i], t[:, i]) for i, axis in enumerate("xyz")}


def pose_metrics(pred: np.ndarray, target: np.ndarray) -> dict[str, float]:
    """(N, 6) relative poses -> RMSE of the position error (m) and of the rotation-vector error (rad)."""
    return {"rmse_position_m": _rmse_norm(pred[:, :3], target[:, :3]),
            "rmse_rotation_rad": _rmse_norm(pred[:, 3:], target[:, 3:])}


def joystick_metrics(pred: np.ndarray, target: np.ndarray) -> dict[str, float]:
    return {f"rmse_{name}_rad": _rmse(pred[:, i], target[:, i]) for i, name in enumerate(("roll", "pitch", "yaw"))}


TRACE_NAMES = {
    "pose": ("dx (m)", "dy (m)", "dz (m)", "rotation x (rad)", "rotation y (rad)", "rotation z (rad)"),
    "joystick": ("roll (rad)", "pitch (rad)", "yaw (rad)"),
}
"""Output names of the temporal tasks, for the plots of predicted vs true over time."""


# ------------------------------------------------------------------------------------------------ head
class TemporalProbeHead(nn.Module):
    """Tokens of S windows per sample (B S, N, D) -> (B, S, outputs): an attentive pooler per window, a fixed
    sinusoidal embedding of the window's index, one causal pre-norm transformer block, then an MLP at every
    window."""

    def __init__(self, width: int, outputs: int, heads: int = 4, hidden: int = 256):
        super().__init__()
        self.pool = AttentivePooler(width, heads)
        self.register_buffer("bands", frequency_bands(width, 1), persistent=False)
        self.block = Block(width, heads, causal=True)
        self.head = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, hidden), nn.GELU(), nn.Linear(hidden, outputs))

    def forward(self, tokens: Tensor, seq: int) -> Tensor:
        x = self.pool(tokens)  # (B S, D)
        x = x.reshape(-1, seq, x.shape[-1])  # (B, S, D)
        index = torch.arange(seq, device=x.device, dtype=torch.float32)[:, None]  # (S, 1)
        x = x + sincos_embedding(index, self.bands, x.shape[-1]).to(x.dtype)  # (B, S, D)
        return self.head(self.block(x))  # (B, S, outputs)
