"""Benchmark: the batched env with Digit 360 touch on vs off, touch collection, and the session reader, in one run.

``tactile_over_plain`` is the env steps/s with touch on (sensors, contact history, the lazy `tactile` group) over
the same env without touch, measured alternately in the same process. ``collect_samples_per_s`` counts fingertip
windows recorded per second of wall time (`rotate collect`: 30 windows per simulated second and fingertip);
``reader_windows_per_s`` is how many Sparsh-X windows (one fingertip: image, audio log-mel, IMU, pressure + labels)
one loader process renders per second from those sessions; ``obs_windows_per_s`` the same for the env's own
`tactile` observation. The last line printed is a JSON object.

    python scripts/bench_tactile.py
    python scripts/bench_tactile.py --num-envs 32 --env-steps 8192 --reader-windows 256
    python scripts/bench_tactile.py --hand digit360_v4       # the vendor-kinematics hand, generation-2 touch
"""

from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from envs.config import EnvConfig
from envs.constants import DEFAULT_HAND
from envs.core import RotateCupVec, random_steps_per_s
from envs.sensors.digit360 import FINGERS
from rotation.configs import script_main
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.jobs import collect


@dataclass
class Config:
    """Benchmark settings."""

    num_envs: int = 16
    """Simulations stepped together (env and collection)."""
    env_steps: int = 4096
    """Env transitions timed per configuration (touch on, touch off), split into alternating rounds."""
    rounds: int = 2
    """Alternating on/off rounds (evens out a machine whose load changes during the run)."""
    collect_steps: int = 60
    """Policy steps per collected episode (one episode per env; >= 30 so that windows exist)."""
    reader_windows: int = 128
    """Windows read from the collected sessions for the reader rate."""
    object: str = "cup"
    """Object (envs.objects)."""
    hand: str = DEFAULT_HAND
    """Digit 360 hand: 'digit360' (generation-1 touch) or 'digit360_v4' (the vendor's kinematics, generation 2)."""
    nthread: int = 0
    """MuJoCo threads (0 = one per CPU core, at most num_envs)."""
    seed: int = 0
    """Seed of the envs and of the reader's window order."""


def bench_env(cfg: Config, tactile: bool, steps: int) -> float:
    """Env transitions per second of the batched core (uniform random actions, done envs reset)."""
    env = RotateCupVec(EnvConfig(object=cfg.object, tactile=tactile, hand=cfg.hand), num_envs=cfg.num_envs,
                       seed=cfg.seed, nthread=cfg.nthread or None)
    try:
        return random_steps_per_s(env, steps, cfg.seed)
    finally:
        env.close()


def bench_obs_render(cfg: Config) -> float:
    """Windows per second when the env's `tactile` observation is rendered (all fingertips of all envs)."""
    env = RotateCupVec(EnvConfig(object=cfg.object, tactile=True, hand=cfg.hand), num_envs=cfg.num_envs, seed=cfg.seed,
                       nthread=cfg.nthread or None)
    env.reset()
    obs, *_ = env.step(np.zeros((cfg.num_envs, 16)))
    obs["tactile"][0]["index"]["image"]  # warm the per-process tables
    obs, *_ = env.step(np.zeros((cfg.num_envs, 16)))
    start = time.perf_counter()
    obs["tactile"].numpy()
    return cfg.num_envs * len(FINGERS) / (time.perf_counter() - start)


def bench_reader(paths: list[Path], n: int, seed: int) -> tuple[float, int]:
    """Windows per second read + rendered by one loader process, and the number of windows available."""
    ds = TouchWindows(paths)
    if len(ds) == 0:
        raise ValueError("the collected sessions are too short for a window; raise --collect-steps")
    order = np.random.default_rng(seed).integers(0, len(ds), size=n)
    ds[int(order[0])]  # warm caches (per-process tables, the sessions' contact tracks)
    start = time.perf_counter()
    for i in order:
        ds[int(i)]
    return n / (time.perf_counter() - start), len(ds)


def run(cfg: Config) -> dict:
    """All measurements; prints a short summary and, last, the JSON result (also returned)."""
    if min(cfg.num_envs, cfg.env_steps, cfg.rounds, cfg.reader_windows) < 1 or cfg.collect_steps < 30:
        raise ValueError("num_envs, env_steps, rounds and reader_windows must be >= 1 and collect_steps >= 30")
    torch.set_num_threads(1)  # the loader measurement is per process, as in a DataLoader worker
    walls = {False: 0.0, True: 0.0}
    per_round = max(cfg.num_envs, cfg.env_steps // cfg.rounds)
    for _ in range(cfg.rounds):
        for tactile in (False, True):
            walls[tactile] += per_round / bench_env(cfg, tactile, per_round)
    plain, touch = cfg.rounds * per_round / walls[False], cfg.rounds * per_round / walls[True]
    obs_wps = bench_obs_render(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        ccfg = collect.Config(episodes=cfg.num_envs, out=Path(tmp), num_envs=cfg.num_envs, seed=cfg.seed,
                              object=cfg.object, episode_steps=cfg.collect_steps, progress=False,
                              hand=cfg.hand if cfg.hand != "digit360" else "auto")
        stats = collect.run(ccfg)
        reader_wps, available = bench_reader(find_sessions(tmp), cfg.reader_windows, cfg.seed)
    result = {
        "hand": cfg.hand,
        "num_envs": cfg.num_envs,
        "plain_steps_per_s": round(plain, 1),
        "tactile_steps_per_s": round(touch, 1),
        "tactile_over_plain": round(touch / plain, 4),
        "collect_steps_per_s": round(stats["steps_per_s"], 1),
        "collect_samples_per_s": round(stats["samples_per_s"], 1),
        "reader_windows_per_s": round(reader_wps, 1),
        "reader_windows_available": available,
        "obs_windows_per_s": round(obs_wps, 1),
    }
    print(f"env: {plain:,.0f} steps/s without touch, {touch:,.0f} with ({100 * touch / plain:.0f}%); collection "
          f"{stats['samples_per_s']:,.0f} fingertip windows/s; reader {reader_wps:,.0f} windows/s per process; "
          f"env tactile obs {obs_wps:,.0f} windows/s")
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
