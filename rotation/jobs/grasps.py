"""Generate initial grasps with Hora's acceptance rule and write a grasp cache per object.

For each object and each randomization scale bucket: sample the canonical closed pose + U(-noise, noise) per joint,
close the fingers on the floating object, release it under gravity for 50 policy steps, and keep the grasp if all
four fingertips are within 10 cm of the object, at least two touch it, and it did not fall.

    rotate grasps --objects cup cylinder --per-scale 100 --out grasps/
    rotate view --object cup --grasp-cache grasps/grasps_cup.npz --out cup.png

The files are `OUT/grasps_<object>.npz`; pass one to the env as `grasp_cache=...` (or `--grasp-cache`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from envs.config import RandomizationConfig
from envs.grasps import generate_grasps
from envs.objects import get_object


@dataclass
class Config:
    objects: tuple[str, ...] = ("cup",)
    """Objects to generate grasps for (names in envs.objects.OBJECTS)."""
    scales: tuple[float, ...] = RandomizationConfig().scales
    """Scale buckets (the env picks the nearest bucket for each env's scale)."""
    per_scale: int = 100
    """Accepted grasps to keep per scale."""
    seed: int = 0
    """Seed of the pose sampling."""
    batch_size: int = 128
    """Candidate grasps simulated together."""
    noise: float = 0.25
    """Joint noise U(-noise, noise) rad around the canonical pose (Hora: 0.25)."""
    out: Path = Path("grasps")
    """Output directory."""


def run(cfg: Config) -> list[Path]:
    for name in cfg.objects:
        get_object(name)  # fail before any work on an unknown name
    if cfg.per_scale < 1 or cfg.batch_size < 1:
        raise ValueError(f"per_scale and batch_size must be >= 1, got {cfg.per_scale}, {cfg.batch_size}")
    RandomizationConfig(scales=tuple(cfg.scales))  # validates the scales
    written = []
    for name in cfg.objects:
        start = time.time()
        bar = tqdm(total=cfg.per_scale * len(cfg.scales), desc=f"grasps {name}", unit="grasp")
        done: dict[float, int] = {}

        def progress(scale: float, accepted: int, wanted: int, bar=bar, done=done) -> None:
            done[scale] = min(accepted, wanted)
            bar.n = sum(done.values())
            bar.refresh()

        cache = generate_grasps(name, tuple(cfg.scales), cfg.per_scale, seed=cfg.seed, batch_size=cfg.batch_size,
                                noise=cfg.noise, progress=progress)
        bar.close()
        path = cfg.out / f"grasps_{name}.npz"
        cache.save(path)
        written.append(path)
        print(f"{name}: {cache.grasps.shape[0]} scales x {cache.grasps.shape[1]} grasps -> {path} "
              f"({time.time() - start:.1f} s)")
    return written
