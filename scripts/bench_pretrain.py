"""Benchmark: how fast touch windows reach the encoder during pretraining, rendered on the fly vs from the cache,
and pretraining steps per second.

Collects a few simulated sessions (random policy, touch on) into a temporary directory, then measures:

- ``loader_windows_per_s_live``: windows per second a DataLoader with ``workers`` processes renders from the
  sessions (TouchWindows; images, audio, IMU and pressure from contact fields) and delivers, including the batched
  log-mel filterbank on ``device`` (what ``rotate pretrain`` without ``--cache`` feeds the model);
- ``cache_windows_per_s``: windows per second ``rotate cache-touch`` renders into the cache (``workers``
  processes, one session each);
- ``loader_windows_per_s``: windows per second the same DataLoader delivers from the cache, moved to ``device``
  and turned into model inputs (``preprocess``);
- ``pretrain_samples_per_s``: windows per second of `rotate pretrain` itself (``size``, from the cache), the
  second half of ``steps`` (after start-up).

The last line printed is a JSON object.

    python scripts/bench_pretrain.py
    python scripts/bench_pretrain.py --workers 8 --device cuda --size small --batch-size 64 --steps 40
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.utils.data import DataLoader, Dataset

from rotation.configs import script_main
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.data.window_cache import CachedWindows, build_cache
from rotation.jobs import collect
from rotation.tactile.loading import to_device
from rotation.tactile.models.sparshx import SparshX, SparshXConfig
from rotation.tactile.pretrain import job as pretrain
from rotation.tactile.runtime import resolve_device


@dataclass
class Config:
    """Benchmark settings."""

    sessions: int = 4
    """Simulated sessions to collect (one per env)."""
    session_steps: int = 80
    """Policy steps per session (20 Hz; windows start after 1.12 s)."""
    stride: int = 1
    """Window stride in image frames."""
    workers: int = 2
    """DataLoader worker processes (loaders and the cache build)."""
    batch_size: int = 32
    """Windows per batch (loaders and pretraining)."""
    batches: int = 8
    """Batches timed per loader (after one untimed batch that starts the workers)."""
    device: str = "auto"
    """Where batches go and pretraining runs (auto: a GPU if there is one)."""
    size: str = "tinier"
    """Encoder size of the pretraining measurement."""
    steps: int = 8
    """Pretraining steps (the second half is timed)."""
    threads: int = 0
    """torch CPU threads of this process (0 = torch's default)."""
    seed: int = 0
    """Seed of the collection."""


def loader_rate(dataset: Dataset, cfg: Config, device: torch.device) -> float:
    """Windows per second delivered to ``device`` as model inputs by a DataLoader over ``dataset``."""
    encoder = SparshX(SparshXConfig(size="tinier")).to(device)
    loader = DataLoader(dataset, batch_size=cfg.batch_size, shuffle=True, num_workers=cfg.workers,
                        pin_memory=device.type == "cuda", generator=torch.Generator().manual_seed(cfg.seed))
    it = iter(loader)
    encoder.preprocess(to_device(next(it), device))  # starts the workers
    count, start = 0, time.perf_counter()
    for _ in range(cfg.batches):
        try:
            batch = next(it)
        except StopIteration:
            it = iter(loader)
            batch = next(it)
        inputs = encoder.preprocess(to_device(batch, device))
        count += len(batch["time"])
    if device.type == "cuda":
        torch.cuda.synchronize()
    del inputs
    return count / (time.perf_counter() - start)


def run(cfg: Config) -> dict:
    if min(cfg.sessions, cfg.batch_size, cfg.batches, cfg.steps, cfg.stride) < 1 or cfg.session_steps < 30 \
            or cfg.workers < 0 or cfg.threads < 0:
        raise ValueError("sessions, batch_size, batches, steps and stride must be >= 1, session_steps >= 30, "
                         "workers and threads >= 0")
    device = resolve_device(cfg.device)
    threads = torch.get_num_threads()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    try:
        return _measure(cfg, device)
    finally:
        torch.set_num_threads(threads)


def _measure(cfg: Config, device: torch.device) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        collect.run(collect.Config(out=root / "sessions", episodes=cfg.sessions, num_envs=cfg.sessions,
                                   episode_steps=cfg.session_steps, seed=cfg.seed, random_scale=0.15,
                                   progress=False))
        paths = find_sessions(root / "sessions")
        live = TouchWindows(paths, stride=cfg.stride, labels=(), audio_features=False)
        live_wps = loader_rate(live, cfg, device)
        start = time.perf_counter()
        build_cache(paths, root / "cache", stride=cfg.stride, workers=cfg.workers, progress=False)
        cache_wps = len(live) / (time.perf_counter() - start)
        cached = CachedWindows(root / "cache", labels=())
        cached_wps = loader_rate(cached, cfg, device)
        half = max(1, cfg.steps // 2)
        pcfg = pretrain.Config(sessions=(root / "sessions",), cache=root / "cache", out=root / "run", size=cfg.size,
                               stride=cfg.stride, steps=2 * half, batch_size=cfg.batch_size, num_workers=cfg.workers,
                               device=str(device), log_every=half, checkpoint_every=10**9, stats_windows=32,
                               progress=False, seed=cfg.seed)
        history = pretrain.run(pcfg)["history"]
    result = {
        "device": str(device),
        "workers": cfg.workers,
        "batch_size": cfg.batch_size,
        "windows": len(live),
        "loader_windows_per_s_live": round(live_wps, 1),
        "cache_windows_per_s": round(cache_wps, 1),
        "loader_windows_per_s": round(cached_wps, 1),
        "cached_over_live": round(cached_wps / live_wps, 2),
        "pretrain_size": cfg.size,
        "pretrain_samples_per_s": round(history[-1]["samples_per_s"], 1),
        "pretrain_data_wait_fraction": round(history[-1]["data_wait_fraction"], 3),
    }
    print(f"windows to {device} with {cfg.workers} worker(s): {live_wps:,.0f}/s rendered on the fly, "
          f"{cached_wps:,.0f}/s from the cache (built at {cache_wps:,.0f}/s); pretraining {cfg.size}: "
          f"{result['pretrain_samples_per_s']:,.0f} windows/s (waiting for data "
          f"{100 * result['pretrain_data_wait_fraction']:.0f}% of the time)")
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
