"""Benchmark: the MuJoCo Warp backend against the CPU backend, env control steps/s and PPO training steps/s.

Three measurements in one run:

- warp env: RotateCupWarp with each of `worlds` worlds on `device`, stepped with random actions and finished
  worlds reset on the device (what training does); control steps/s = policy steps x worlds per second;
- warp train: the GPU teacher's PPO iteration (rotation.train.teacher_warp.WarpPPO: rollout of n_steps x
  train_worlds transitions on the device, then n_epochs of minibatch updates), transitions per second;
- cpu env: the CPU core (envs.core.RotateCupVec, mujoco.batch on this machine's cores) with `cpu_envs` envs under
  random actions, control steps/s the same way.

The last line printed is a JSON object with `warp_env_steps_per_s` (the best over `worlds`),
`warp_train_steps_per_s` and `cpu_env_steps_per_s`. On a GPU:

    python scripts/bench_warp.py
    python scripts/bench_warp.py --worlds 1024 4096 16384 --train-worlds 8192
    python scripts/bench_warp.py --device cpu --worlds 2 4 --train-worlds 4 --steps 3   # Warp's CPU device
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass

import torch

from envs.config import EnvConfig
from envs.core import RotateCupVec, random_steps_per_s
from envs.validation import check_int, check_seed, check_types
from rotation.configs import num_cores, script_main


@dataclass
class Config:
    """Benchmark settings."""

    worlds: tuple[int, ...] = (1024, 2048, 4096, 8192, 16384)
    """Numbers of Warp worlds to measure env steps/s at."""
    device: str = "cuda"
    """Device of the Warp worlds and of PPO: 'cuda' or 'cpu' (Warp's CPU device, slow)."""
    steps: int = 50
    """Timed control steps per world count (after `warmup`)."""
    warmup: int = 5
    """Untimed control steps first (the first ones compile kernels and capture the CUDA graph)."""
    train_worlds: int = 8192
    """Worlds of the PPO measurement (0 skips it); the GPU recipe's 8192."""
    train_iterations: int = 3
    """Timed PPO iterations (after one untimed)."""
    n_steps: int = 8
    """PPO horizon (GPU recipe: 8)."""
    n_epochs: int = 5
    """PPO epochs per iteration (GPU recipe: 5)."""
    cpu_envs: int = 256
    """Envs of the CPU backend measurement (the CPU teacher's 256; 0 skips it)."""
    cpu_steps: int = 50
    """Control steps of every CPU env."""
    nthread: int = 0
    """MuJoCo threads of the CPU backend (0 = every core of this process)."""
    seed: int = 0
    """Seed of the envs and actions."""
    hand: str = "digit360"
    """Hand variant of every measurement, the same on both backends: one whose physics the warp backend simulates
    (rotation.sim_warp.core.simulated_hands; not yet the digit360_v4 hand's)."""

    def __post_init__(self) -> None:
        check_types(self)
        if not self.worlds or not all(1 <= w <= 65_536 for w in self.worlds):
            raise ValueError(f"worlds must list numbers of worlds in [1, 65536], got {self.worlds!r}")
        for name, low in (("steps", 1), ("warmup", 0), ("train_worlds", 0), ("train_iterations", 1), ("n_steps", 1),
                          ("n_epochs", 1), ("cpu_envs", 0), ("cpu_steps", 1), ("nthread", 0)):
            check_int(name, getattr(self, name), low, 10**9)
        check_seed("seed", self.seed)
        from rotation.sim_warp.core import simulated_hands

        if self.hand not in simulated_hands():
            raise ValueError(f"hand: the warp backend simulates the {' and '.join(simulated_hands())} hands, not "
                             f"{self.hand!r}")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def warp_env_rate(cfg: Config, worlds: int) -> float:
    """Control steps/s (x worlds) of RotateCupWarp under uniform random actions, finished worlds reset."""
    from rotation.sim_warp.core import RotateCupWarp, WarpConfig

    env = RotateCupWarp(EnvConfig(hand=cfg.hand), num_envs=worlds, seed=cfg.seed,
                        warp_cfg=WarpConfig(device=cfg.device))
    dev = env.torch_device
    gen = torch.Generator(device=dev).manual_seed(cfg.seed)
    env.reset(seed=cfg.seed)

    def step() -> None:
        actions = torch.rand((worlds, 16), generator=gen, device=dev) * 2 - 1
        _, _, terminated, truncated, _ = env.step(actions)
        env.reset_done(terminated | truncated)

    for _ in range(cfg.warmup):
        step()
    _sync(dev)
    start = time.perf_counter()
    for _ in range(cfg.steps):
        step()
    _sync(dev)
    wall = time.perf_counter() - start
    env.close()
    return cfg.steps * worlds / wall


def warp_train_rate(cfg: Config) -> float:
    """Transitions/s of the GPU teacher's PPO (rollout + update) with the GPU recipe's settings."""
    from rotation.sim_warp.core import RotateCupWarp, WarpConfig
    from rotation.train.teacher_config import Config as TeacherConfig
    from rotation.train.teacher_warp import WarpPPO

    n = cfg.train_worlds
    tcfg = TeacherConfig(backend="warp", hand=cfg.hand, device=cfg.device, num_envs=n, n_steps=cfg.n_steps,
                         n_epochs=cfg.n_epochs, batch_size=max(2, n * cfg.n_steps // 4), learning_rate=5e-3,
                         progress=False)
    env_cfg = tcfg.env_config()
    env = RotateCupWarp(env_cfg, num_envs=n, seed=cfg.seed, warp_cfg=WarpConfig(device=cfg.device))
    learner = WarpPPO(tcfg, env, env_cfg)
    learner.iteration()  # untimed: compiles, captures, warms the allocator
    _sync(env.torch_device)
    start = time.perf_counter()
    for _ in range(cfg.train_iterations):
        learner.iteration()
    _sync(env.torch_device)
    wall = time.perf_counter() - start
    env.close()
    return cfg.train_iterations * n * cfg.n_steps / wall


def cpu_env_rate(cfg: Config) -> tuple[float, int]:
    """Control steps/s (x envs) of the CPU core under uniform random actions; returns (rate, threads)."""
    nthread = cfg.nthread or num_cores()
    env = RotateCupVec(EnvConfig(hand=cfg.hand), num_envs=cfg.cpu_envs, seed=cfg.seed, nthread=nthread)
    random_steps_per_s(env, cfg.cpu_envs * max(1, cfg.warmup), seed=cfg.seed)  # warm-up
    rate = random_steps_per_s(env, cfg.cpu_envs * cfg.cpu_steps, seed=cfg.seed)
    env.close()
    return rate, nthread


def run(cfg: Config) -> dict:
    """All measurements; prints a table and, last, the JSON result (also returned)."""
    from rotation.sim_warp.core import resolve_device

    resolve_device(cfg.device)  # a clear error without a GPU, before anything runs
    env_rates = {w: warp_env_rate(cfg, w) for w in cfg.worlds}
    train_rate = warp_train_rate(cfg) if cfg.train_worlds else None
    cpu_rate, threads = cpu_env_rate(cfg) if cfg.cpu_envs else (None, 0)
    device_name = torch.cuda.get_device_name(0) if cfg.device.startswith("cuda") else "Warp CPU device"
    print(f"env control steps/s (policy steps x worlds per second), {cfg.steps} timed steps after {cfg.warmup}; "
          f"device: {device_name}")
    print(f"{'backend':10s} {'worlds':>8s} {'steps/s':>12s}")
    for w, r in env_rates.items():
        print(f"{'warp':10s} {w:8d} {r:12,.0f}")
    if cpu_rate is not None:
        print(f"{'cpu':10s} {cfg.cpu_envs:8d} {cpu_rate:12,.0f}   ({threads} MuJoCo threads)")
    if train_rate is not None:
        print(f"PPO training (rollout + {cfg.n_epochs} epochs), {cfg.train_worlds} worlds x horizon {cfg.n_steps}: "
              f"{train_rate:,.0f} transitions/s")
    best = max(env_rates, key=env_rates.get)
    result = {
        "device": cfg.device,
        "device_name": device_name,
        "warp_env_steps_per_s": round(env_rates[best], 1),
        "warp_env_best_worlds": best,
        "warp_env_steps_per_s_by_worlds": {str(w): round(r, 1) for w, r in env_rates.items()},
        "warp_train_steps_per_s": None if train_rate is None else round(train_rate, 1),
        "train_worlds": cfg.train_worlds,
        "cpu_env_steps_per_s": None if cpu_rate is None else round(cpu_rate, 1),
        "cpu_envs": cfg.cpu_envs,
        "cpu_threads": threads,
    }
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
