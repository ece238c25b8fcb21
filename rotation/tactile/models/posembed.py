"""Fixed sinusoidal positional embeddings of Sparsh-X's token grids, computed from two stored buffers.

Each modality owns a :class:`SinCosPosEmbed` with the released checkpoint's buffers
(docs/reference/sparshx_state_dict.md):

- ``frequency_bands`` (ndim, nb): per grid axis the frequencies f_k = 10000^(-k / nb), k = 0..nb-1, with
  nb = ceil(D / (2 ndim)): (2, D/4) for the image and audio grids, (1, D/2) for IMU and pressure.
- ``offset`` (0-dim): the modality's running token offset (image 0, audio 196, IMU 420, pressure 476 for the four
  modalities), added to every coordinate.

What is known of the original and reproduced here: per axis the features sin(c f) and cos(c f), concatenated axis
after axis and truncated to D; coordinates enumerated with "xy" indexing, so on an [H, W] grid flattened row-major
token n gets the coordinates (n % H, n // H) (for the 14 x 16 audio grid this is not the token's (row, column):
the released weights were trained with that enumeration). Not known: how ``offset`` enters (here it is added to the
coordinates, the likeliest reading) and the order of sin and cos (here sin first). Both buffers are loaded from a
checkpoint and the embedding is computed from them (and recomputed whenever they change), so a checkpoint's own
values are what count.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

FREQUENCY_BASE = 10000.0
"""Base of the frequency bands (Transformer positional encoding, Vaswani et al. 2017 section 3.5)."""


def frequency_bands(dim: int, ndim: int) -> Tensor:
    """(ndim, nb) frequencies 10000^(-k / nb), k = 0..nb-1, nb = ceil(dim / (2 ndim)), the same on every axis."""
    nb = math.ceil(dim / (2 * ndim))
    bands = FREQUENCY_BASE ** (-torch.arange(nb, dtype=torch.float32) / nb)  # (nb,)
    return bands.expand(ndim, nb).clone()  # (ndim, nb)


def grid_coordinates(grid: tuple[int, ...]) -> Tensor:
    """(N, ndim) float coordinates of the N = prod(grid) tokens of a row-major flattened grid, "xy" enumeration.

    1-D grid (L,): token n -> (n,). 2-D grid (H, W): token n -> (n % H, n // H) (see the module docstring).
    """
    n = torch.arange(math.prod(grid), dtype=torch.float32)
    if len(grid) == 1:
        return n[:, None]  # (N, 1)
    if len(grid) == 2:
        h = grid[0]
        return torch.stack([n % h, torch.div(n, h, rounding_mode="floor")], dim=1)  # (N, 2)
    raise ValueError(f"grid_coordinates: 1-D or 2-D grids only, got {grid}")


def sincos_embedding(coords: Tensor, bands: Tensor, dim: int) -> Tensor:
    """(N, ndim) coordinates x (ndim, nb) bands -> (N, dim): per axis [sin(c f), cos(c f)], axes concatenated,
    truncated to ``dim``."""
    angles = coords[:, :, None] * bands[None]  # (N, ndim, nb)
    emb = torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)  # (N, ndim, 2 nb)
    return emb.reshape(coords.shape[0], -1)[:, :dim]  # (N, dim)


class SinCosPosEmbed(nn.Module):
    """Positional embedding (N, D) of one modality's token grid; buffers ``offset`` and ``frequency_bands``."""

    def __init__(self, grid: tuple[int, ...], dim: int, offset: int = 0):
        super().__init__()
        self.grid, self.dim = tuple(grid), dim
        self.register_buffer("offset", torch.tensor(float(offset)))
        self.register_buffer("frequency_bands", frequency_bands(dim, len(self.grid)))
        self._cache: tuple[tuple, Tensor] | None = None

    @property
    def num_tokens(self) -> int:
        return math.prod(self.grid)

    def _cache_key(self) -> tuple | None:
        """Identifies the buffers' current values (storage and in-place version); None when untrackable."""
        try:
            return (self.offset.data_ptr(), self.offset._version, self.frequency_bands.data_ptr(),
                    self.frequency_bands._version, self.offset.device, torch.is_inference_mode_enabled())
        except RuntimeError:  # inference tensors have no version counter
            return None

    def forward(self) -> Tensor:
        key = self._cache_key()
        if key is not None and self._cache is not None and self._cache[0] == key:
            return self._cache[1]
        bands = self.frequency_bands.float()
        coords = grid_coordinates(self.grid).to(bands.device) + self.offset.to(bands)  # (N, ndim)
        emb = sincos_embedding(coords, bands, self.dim)  # (N, D)
        if key is not None and emb.device.type != "meta":  # recomputed only when a buffer changes
            self._cache = (key, emb)
        return emb

    def extra_repr(self) -> str:
        return f"grid={self.grid}, dim={self.dim}"
