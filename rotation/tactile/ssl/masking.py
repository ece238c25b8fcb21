"""Block masks over token sets: the views of DINO-style self-distillation (docs/reference/sparsh.md "Sparsh-X
self-supervised pretraining", docs/reference/sparshx_state_dict.md "Pretraining details").

A view keeps the patch tokens inside one block and drops the others (the encoder gathers the kept tokens, so a
view is cheaper than the full input). Per token set and step:

- one *global* block (scale in ``global_scale``, default 0.48-1.0 of the tokens) and ``num_local`` *local* blocks
  (scale in ``local_scale``, default 0.1-0.48); the teacher sees the global view, the student every view;
- a token set laid out on a grid (h, w) (image and audio patches) gets rectangular blocks, square where the grid
  allows (side about sqrt(h w s)); a 1-D set (IMU, pressure: a grid (n,)) gets contiguous segments of about n s;
- the block size is drawn once per step and token set, positions per sample; token sets are masked independently
  (so masking is also cross-modal);
- the local blocks are placed first and the global block avoids them: among ``tries`` random placements the first
  that leaves at least ``min_keep`` of its tokens outside every local block wins (else the one leaving the most;
  if even that leaves fewer than ``min_keep``, the global view keeps its whole block, overlap included);
- every view keeps at least ``min_keep`` tokens; the global view's kept tokens are truncated to the batch minimum
  (a random subset per sample) so a view is one (B, K) index tensor.

Indices are row-major over the grid (the order in which the encoder flattens its patches), sorted, in [0, h w).
Everything is a pure function of the numpy generator passed in, so a step's masks are reproducible from a seed.

:func:`sample_multi_views` draws DINOv2-style views instead (Sparsh-skin, docs/reference/sparsh.md): several global
blocks (40-100 %) and local blocks (10-40 %) placed independently, one size per kind, step and set, and inside each
global view an iBOT mask (a contiguous run of 10-50 % of its tokens, on half of the samples) that the student sees
as the mask token. Over Sparsh-skin's 1-D taxel order a block is a run of consecutive taxels, each token all 10
frames of its taxel: a view keeps the same taxels across time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from envs.validation import check_int, check_types


@dataclass(frozen=True)
class MaskConfig:
    """How the views of one step are drawn (defaults: Sparsh v1's scale ranges,
    docs/reference/sparshx_state_dict.md)."""

    global_scale: tuple[float, float] = (0.48, 1.0)
    """Range of the global block's size, as a fraction of the token set."""
    local_scale: tuple[float, float] = (0.1, 0.48)
    """Range of a local block's size, as a fraction of the token set."""
    num_local: int = 4
    """Local views per token set (the student sees 1 + num_local views, the teacher the global one)."""
    min_keep: int = 4
    """Fewest tokens a view keeps (DINOv2's block masking: at least 4 patches)."""
    tries: int = 16
    """Placements tried for the global block to avoid the local ones."""

    def __post_init__(self) -> None:
        check_types(self, prefix="mask.")
        for name in ("global_scale", "local_scale"):
            lo_hi = tuple(getattr(self, name))
            if not all(math.isfinite(v) for v in lo_hi) or not 0.0 < lo_hi[0] <= lo_hi[1] <= 1.0:
                raise ValueError(f"mask.{name} must be (low, high) with 0 < low <= high <= 1, got {lo_hi}")
        check_int("mask.num_local", self.num_local, 1, 64)
        check_int("mask.min_keep", self.min_keep, 1, 4096)
        check_int("mask.tries", self.tries, 1, 1000)

    @property
    def num_views(self) -> int:
        return 1 + self.num_local


def block_shape(grid: tuple[int, ...], scale: float, min_keep: int = 1) -> tuple[int, int]:
    """(rows, cols) of a block covering about ``scale`` of a (h, w) grid (or a (n,) segment: rows = 1), with at
    least ``min_keep`` tokens: square with side round(sqrt(h w s)) where it fits, else as wide as the grid allows
    with the other side stretched to keep the area."""
    h, w = _hw(grid)
    area = max(scale * h * w, float(min_keep))
    if h == 1:
        return 1, min(w, max(min_keep, round(area)))
    bh = min(h, max(1, round(math.sqrt(area))))
    bw = min(w, max(1, round(area / bh)))
    while bh * bw < min_keep:  # a tiny scale on a small grid: grow the shorter side that still fits
        if (bw <= bh or bh == h) and bw < w:
            bw += 1
        else:
            bh += 1
    return bh, bw


def _hw(grid: tuple[int, ...]) -> tuple[int, int]:
    if len(grid) == 1:
        return 1, int(grid[0])
    if len(grid) == 2:
        return int(grid[0]), int(grid[1])
    raise ValueError(f"a token grid is (n,) or (h, w), got {grid}")


def _inside(h: int, w: int, top: np.ndarray, left: np.ndarray, bh: int, bw: int) -> np.ndarray:
    """(..., h w) bool: tokens inside the block at (top, left) of size (bh, bw), for arrays of positions (...)."""
    rows = np.arange(h * w) // w
    cols = np.arange(h * w) % w
    t, c = top[..., None], left[..., None]
    return (rows >= t) & (rows < t + bh) & (cols >= c) & (cols < c + bw)


def _block_indices(w: int, top: np.ndarray, left: np.ndarray, bh: int, bw: int) -> np.ndarray:
    """(B, bh bw) sorted row-major indices of the blocks at (top, left) (B,)."""
    rows = top[:, None, None] + np.arange(bh)[None, :, None]  # (B, bh, 1)
    cols = left[:, None, None] + np.arange(bw)[None, None, :]  # (B, 1, bw)
    return (rows * w + cols).reshape(len(top), bh * bw)


def sample_set_views(grid: tuple[int, ...], batch: int, cfg: MaskConfig, rng: np.random.Generator
                     ) -> list[np.ndarray]:
    """The views of one token set: [global (B, K_g), local_1 (B, K_l), ...] int64 kept-token indices."""
    h, w = _hw(grid)
    n = h * w
    if n < cfg.min_keep:
        raise ValueError(f"a token set of {n} tokens cannot keep min_keep={cfg.min_keep} tokens per view")
    s_global = rng.uniform(*cfg.global_scale)
    s_local = rng.uniform(*cfg.local_scale)
    gh, gw = block_shape(grid, s_global, cfg.min_keep)
    lh, lw = block_shape(grid, s_local, cfg.min_keep)

    # local blocks first: (B, L) positions, their union (B, n)
    lt = rng.integers(0, h - lh + 1, size=(batch, cfg.num_local))
    ll = rng.integers(0, w - lw + 1, size=(batch, cfg.num_local))
    locals_ = [_block_indices(w, lt[:, j], ll[:, j], lh, lw) for j in range(cfg.num_local)]
    union = _inside(h, w, lt, ll, lh, lw).any(axis=1) if cfg.num_local else np.zeros((batch, n), bool)

    # the global block: first placement leaving >= min_keep tokens outside the locals, else the best one
    gt = rng.integers(0, h - gh + 1, size=(batch, cfg.tries))
    gl = rng.integers(0, w - gw + 1, size=(batch, cfg.tries))
    inside = _inside(h, w, gt, gl, gh, gw)  # (B, T, n)
    free = inside & ~union[:, None, :]
    counts = free.sum(axis=-1)  # (B, T)
    ok = counts >= cfg.min_keep
    pick = np.where(ok.any(axis=1), ok.argmax(axis=1), counts.argmax(axis=1))  # (B,)
    rows = np.arange(batch)
    keep = free[rows, pick]  # (B, n)
    short = keep.sum(axis=1) < cfg.min_keep
    keep[short] = inside[rows, pick][short]  # locals cover the block: overlap allowed rather than < min_keep
    k = int(keep.sum(axis=1).min())
    # truncate to the batch minimum: a random subset of each sample's kept tokens, sorted
    keys = np.where(keep, rng.random((batch, n)), 2.0)
    global_idx = np.sort(np.argsort(keys, axis=1, kind="stable")[:, :k], axis=1)
    return [global_idx.astype(np.int64), *(x.astype(np.int64) for x in locals_)]


def sample_views(grids: Mapping[str, tuple[int, ...]], batch: int, cfg: MaskConfig, rng: np.random.Generator,
                 device: torch.device | str | None = None) -> list[dict[str, torch.Tensor]]:
    """The views of one step for every token set: ``views[0]`` is the global view, ``views[1:]`` the local ones;
    each a dict {set name: (B, K) int64 tensor} ready for ``encoder(inputs, keep=view)``.

    Token sets are drawn in the order of ``grids`` from one generator (fix the order for reproducible masks).
    """
    if batch < 1:
        raise ValueError(f"sample_views: batch must be >= 1, got {batch}")
    per_set = {name: sample_set_views(tuple(grid), batch, cfg, rng) for name, grid in grids.items()}
    return [{name: torch.from_numpy(v[i]).to(device) for name, v in per_set.items()} for i in range(cfg.num_views)]


def step_rng(seed: int, step: int, rank: int = 0) -> np.random.Generator:
    """The generator of one training step (masks): a pure function of (seed, step, rank), so resume is exact."""
    return np.random.default_rng([int(seed), int(step), int(rank), 0x6D61736B])  # "mask"


# ------------------------------------------------------------------------ DINOv2-style views (Sparsh-skin)
@dataclass(frozen=True)
class ViewMaskConfig:
    """DINOv2-style views of a step (defaults: Sparsh-skin, docs/reference/sparsh.md): ``num_global`` global and
    ``num_local`` local blocks placed independently (no avoidance), and iBOT masks inside the global views. Errors
    name the fields ``skin.<field>``: the config is `rotate pretrain`'s ``skin`` group."""

    global_scale: tuple[float, float] = (0.4, 1.0)
    """Range of a global block's size, as a fraction of the token set (Sparsh-skin: 40-100 %)."""
    local_scale: tuple[float, float] = (0.1, 0.4)
    """Range of a local block's size (Sparsh-skin: 10-40 %)."""
    num_global: int = 2
    """Global views (the teacher sees these, the student all views)."""
    num_local: int = 8
    """Local views."""
    min_keep: int = 4
    """Fewest tokens a view keeps."""
    mask_ratio: tuple[float, float] = (0.1, 0.5)
    """Range of the fraction of a student's global-view tokens replaced by the mask token (iBOT;
    docs/reference/sparsh.md: 10-50 %)."""
    mask_probability: float = 0.5
    """Probability that a sample's global view gets an iBOT mask at all (DINOv2: half of them)."""

    def __post_init__(self) -> None:
        check_types(self, prefix="skin.")
        for name in ("global_scale", "local_scale", "mask_ratio"):
            lo_hi = tuple(getattr(self, name))
            if not all(math.isfinite(v) for v in lo_hi) or not 0.0 < lo_hi[0] <= lo_hi[1] <= 1.0:
                raise ValueError(f"skin.{name} must be (low, high) with 0 < low <= high <= 1, got {lo_hi}")
        check_int("skin.num_global", self.num_global, 1, 16)
        check_int("skin.num_local", self.num_local, 0, 64)
        check_int("skin.min_keep", self.min_keep, 1, 4096)
        if not (math.isfinite(self.mask_probability) and 0.0 <= self.mask_probability <= 1.0):
            raise ValueError(f"skin.mask_probability must be in [0, 1], got {self.mask_probability}")


@dataclass
class Views:
    """The views of one step: kept-token indices per view and set, and the iBOT masks of the global views."""

    globals: list[dict[str, torch.Tensor]]
    """num_global x {set: (B, K_g) int64}, one K_g per step and set (so the global views batch together)."""
    locals: list[dict[str, torch.Tensor]]
    """num_local x {set: (B, K_l) int64}."""
    masks: list[dict[str, torch.Tensor]]
    """num_global x {set: (B, K_g) bool}: True = the student sees the mask token there."""


def _place(grid: tuple[int, ...], bh: int, bw: int, count: int, batch: int, rng: np.random.Generator
           ) -> list[np.ndarray]:
    """``count`` blocks of (bh, bw) at independent random positions per sample: count x (B, bh bw) indices."""
    h, w = _hw(grid)
    top = rng.integers(0, h - bh + 1, size=(batch, count))
    left = rng.integers(0, w - bw + 1, size=(batch, count))
    return [_block_indices(w, top[:, j], left[:, j], bh, bw).astype(np.int64) for j in range(count)]


def _ibot_masks(k: int, count: int, batch: int, cfg: ViewMaskConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """count x (B, k) bool: per sample (with probability ``mask_probability``) one contiguous run of about
    ratio x k of the kept tokens (a block over the set's order), ratio drawn from ``mask_ratio``, at least 1."""
    out = []
    pos = np.arange(k)[None]
    for _ in range(count):
        apply = rng.random(batch) < cfg.mask_probability
        m = np.clip(np.round(rng.uniform(*cfg.mask_ratio, size=batch) * k), 1, k).astype(np.int64)  # (B,)
        start = (rng.random(batch) * (k - m + 1)).astype(np.int64)  # (B,) in [0, k - m]
        out.append(apply[:, None] & (pos >= start[:, None]) & (pos < (start + m)[:, None]))
    return out


def sample_multi_views(grids: Mapping[str, tuple[int, ...]], batch: int, cfg: ViewMaskConfig,
                       rng: np.random.Generator, device: torch.device | str | None = None) -> Views:
    """The views of one step for every token set (grids as in :func:`sample_views`; a 1-D set (n,) gets
    contiguous segments of its order, e.g. the taxel order). Per set, one global and one local block size per
    step, positions per sample; the global views keep 40-100 %, the local ones 10-40 % by default. Everything is
    a pure function of ``rng``."""
    if batch < 1:
        raise ValueError(f"sample_multi_views: batch must be >= 1, got {batch}")
    per: dict[str, tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]] = {}
    for name, grid in grids.items():
        grid = tuple(grid)
        h, w = _hw(grid)
        if h * w < cfg.min_keep:
            raise ValueError(f"a token set of {h * w} tokens cannot keep min_keep={cfg.min_keep} tokens per view")
        gh, gw = block_shape(grid, rng.uniform(*cfg.global_scale), cfg.min_keep)
        lh, lw = block_shape(grid, rng.uniform(*cfg.local_scale), cfg.min_keep)
        g = _place(grid, gh, gw, cfg.num_global, batch, rng)
        loc = _place(grid, lh, lw, cfg.num_local, batch, rng)
        per[name] = (g, loc, _ibot_masks(gh * gw, cfg.num_global, batch, cfg, rng))

    def views(i: int, j: int) -> dict[str, torch.Tensor]:
        return {name: torch.from_numpy(v[i][j]).to(device) for name, v in per.items()}

    return Views(globals=[views(0, j) for j in range(cfg.num_global)],
                 locals=[views(1, j) for j in range(cfg.num_local)],
                 masks=[views(2, j) for j in range(cfg.num_global)])
