"""The imitation policy: an action-chunking transformer (after ACT, Zhao et al. 2023) over the wrist camera's frame,
proprioception and, when it reads touch, one frozen embedding per fingertip.

Tokens: the image through a small convolutional stem (four stride-2 convolutions: 160 x 120 -> 10 x 8 = 80 tokens)
with a learned position embedding; one proprioception token; one token per fingertip (its embedding, projected,
plus a learned fingertip embedding). A transformer encoder mixes them; ``chunk`` learned queries cross-attend to its
output in a transformer decoder and each gives one action of the chunk: the policy predicts the next ``chunk``
actions at once. Inputs and actions are standardized with the demonstrations' statistics, kept in the model.
Left out from ACT: its conditional-VAE style latent (the scripted expert's demonstrations are close to
deterministic given the state) and the ImageNet-pretrained ResNet backbone (this stack downloads no weights).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn


@dataclass(frozen=True)
class PolicyConfig:
    image_size: tuple[int, int] = (160, 120)
    """Camera width, height (pixels), at least 16 each."""
    proprio_dim: int = 23
    """Wrist pose (7) + joints (16)."""
    touch_dim: int = 0
    """Width of a fingertip's touch embedding; 0: the policy reads no touch."""
    fingers: int = 4
    chunk: int = 10
    """Actions predicted at once."""
    action_dim: int = 6
    width: int = 128
    heads: int = 4
    encoder_layers: int = 2
    decoder_layers: int = 2

    def __post_init__(self) -> None:
        w, h = self.image_size
        if w < 16 or h < 16:
            raise ValueError(f"image_size must be at least 16 x 16 pixels, got {self.image_size}")
        if self.width % self.heads:
            raise ValueError(f"width {self.width} must be a multiple of heads {self.heads}")
        for name in ("chunk", "proprio_dim", "action_dim", "encoder_layers", "decoder_layers", "fingers"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")

    def to_json(self) -> dict:
        return asdict(self)


def _grid(pixels: int) -> int:
    """Tokens along one side after the stem's four stride-2 convolutions (each halves, rounding up)."""
    for _ in range(4):
        pixels = (pixels + 1) // 2
    return pixels


class ChunkPolicy(nn.Module):
    """See the module docstring. ``forward`` takes standardized inputs and returns standardized actions."""

    def __init__(self, cfg: PolicyConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.width
        chans = (3, 32, 64, 128, d)
        self.stem = nn.Sequential(*[m for i in range(4) for m in (
            nn.Conv2d(chans[i], chans[i + 1], 5 if i == 0 else 3, stride=2, padding=2 if i == 0 else 1),
            nn.GroupNorm(8, chans[i + 1]), nn.GELU())])
        w, h = cfg.image_size
        self.image_pos = nn.Parameter(torch.zeros(1, _grid(w) * _grid(h), d))
        self.proprio = nn.Linear(cfg.proprio_dim, d)
        self.touch = nn.Linear(cfg.touch_dim, d) if cfg.touch_dim else None
        self.finger = nn.Parameter(torch.zeros(1, cfg.fingers, d)) if cfg.touch_dim else None
        self.kinds = nn.Parameter(torch.zeros(3, d))  # image, proprioception, touch
        layer = dict(d_model=d, nhead=cfg.heads, dim_feedforward=4 * d, dropout=0.1, batch_first=True,
                     norm_first=True, activation="gelu")
        self.encoder = nn.TransformerEncoder(nn.TransformerEncoderLayer(**layer), cfg.encoder_layers,
                                             enable_nested_tensor=False)
        self.decoder = nn.TransformerDecoder(nn.TransformerDecoderLayer(**layer), cfg.decoder_layers)
        self.queries = nn.Parameter(torch.zeros(1, cfg.chunk, d))
        self.head = nn.Linear(d, cfg.action_dim)
        for p in (self.image_pos, self.queries, self.kinds, *([self.finger] if self.finger is not None else [])):
            nn.init.trunc_normal_(p, std=0.02)
        for name, size in (("proprio", cfg.proprio_dim), ("action", cfg.action_dim), ("touch", max(cfg.touch_dim, 1))):
            self.register_buffer(f"{name}_mean", torch.zeros(size))
            self.register_buffer(f"{name}_std", torch.ones(size))

    def set_stats(self, proprio: Tensor, actions: Tensor, touch: Tensor | None) -> None:
        """Standardization from the demonstrations: (N, P) proprioception, (N, 6) actions, (N, F, D) touch."""
        for name, x in (("proprio", proprio), ("action", actions), ("touch", touch)):
            if x is None:
                continue
            x = x.reshape(-1, x.shape[-1]).double()
            getattr(self, f"{name}_mean").copy_(x.mean(0).float())
            getattr(self, f"{name}_std").copy_(x.std(0).clamp_min(1e-6).float())

    def forward(self, image: Tensor, proprio: Tensor, touch: Tensor | None = None) -> Tensor:
        """image (B, H, W, 3) uint8, proprio (B, P), touch (B, F, D) raw -> (B, chunk, action_dim) standardized."""
        x = self.stem(image.permute(0, 3, 1, 2).float() / 255.0 - 0.5)  # (B, d, H/16, W/16)
        tokens = [x.flatten(2).transpose(1, 2) + self.image_pos + self.kinds[0],
                  self.proprio((proprio - self.proprio_mean) / self.proprio_std)[:, None] + self.kinds[1]]
        if self.touch is not None:
            if touch is None:
                raise ValueError("this policy reads touch: give its fingertip embeddings")
            tokens.append(self.touch((touch - self.touch_mean) / self.touch_std) + self.finger + self.kinds[2])
        memory = self.encoder(torch.cat(tokens, dim=1))
        return self.head(self.decoder(self.queries.expand(image.shape[0], -1, -1), memory))

    def actions(self, out: Tensor) -> Tensor:
        """Standardized actions -> physical (m, rad)."""
        return out * self.action_std + self.action_mean
