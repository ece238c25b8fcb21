"""Benchmark: environment steps per second during teacher PPO training vs the batched env alone, in one run.

Both measurements use the same env config, number of envs and MuJoCo threads, so ``train_over_env`` is the share of
the raw simulation speed that training keeps (policy inference during rollouts and the PPO updates take the rest).
It also measures what a rollout costs in CPU time, each part alone: the physics on one MuJoCo thread
(``physics_core_s``), one PPO update (``update_s``) and the policy's inference over the rollout (``inference_s``).
Training has to do all three for every rollout on ``cores`` cores, and cannot step faster than the env alone, so
no scheduling (overlap, threads) of this recipe can pass, on this machine::

    train_over_env_ceiling = min(1, cores x rollout_physics_s / (physics_core_s + update_s + inference_s))

where ``rollout_physics_s`` = rollout / ``env_steps_per_s`` is the wall time of the env alone. The update and the
inference are timed as wall time, a lower bound on their CPU time with any thread count, so the ceiling is an upper
bound. A recipe whose ceiling is under a target needs cheaper updates (smaller networks, fewer epochs), not better
overlap. The last line printed is a JSON object.

    python scripts/bench_train.py --train-steps 65536
    python scripts/bench_train.py --num-envs 128 --n-steps 32 --train-steps 16384
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from envs.core import RotateCupVec, random_steps_per_s
from rotation.configs import num_cores, script_main
from rotation.train import ppo, teacher
from rotation.train.teacher_config import TEACHER_GROUPS
from rotation.train.vec_env import RotateCupSB3VecEnv


@dataclass
class Config:
    """Benchmark settings (PPO settings default to `rotate train-teacher`'s)."""

    num_envs: int = teacher.Config.num_envs
    """Simulations stepped together (train-teacher's default)."""
    env_steps: int = 65_536
    """Env transitions for the env-alone measurement (random actions, resets on done)."""
    train_steps: int = 65_536
    """Env transitions of PPO training to time (rounded up to whole rollouts of num_envs x n_steps)."""
    n_steps: int = teacher.Config.n_steps
    """PPO horizon per env per update."""
    batch_size: int = teacher.Config.batch_size
    """PPO minibatch size."""
    n_epochs: int = teacher.Config.n_epochs
    """PPO passes over each rollout."""
    net_arch: tuple[int, ...] = teacher.Config.net_arch
    """Hidden widths of the actor and critic MLPs (cheaper updates with smaller ones)."""
    object: str = teacher.Config.object
    """Object (envs.objects)."""
    grasp_cache: str = ""
    """Grasp cache file; empty = the one shipped for the object."""
    nthread: int = 0
    """MuJoCo threads (0 = one per CPU core, at most num_envs)."""
    torch_threads: int | None = None
    """torch CPU threads during training; None = train-teacher's default. On a loaded 2-core machine more torch
    threads than free cores can slow PPO down many times over (OpenMP threads spin waiting for each other)."""
    overlap: bool = teacher.Config.overlap
    """Collect the next rollout while PPO updates (train-teacher's default); --no-overlap times plain PPO."""
    seed: int = 0
    """Seed of the envs and of torch."""


def teacher_config(cfg: Config, out: Path) -> teacher.Config:
    threads = {} if cfg.torch_threads is None else {"torch_threads": cfg.torch_threads}
    return teacher.Config(out=out, object=cfg.object, num_envs=cfg.num_envs, total_steps=cfg.train_steps,
                          seed=cfg.seed, n_steps=cfg.n_steps, n_epochs=cfg.n_epochs, net_arch=tuple(cfg.net_arch),
                          grasp_cache=cfg.grasp_cache,
                          batch_size=min(cfg.batch_size, cfg.num_envs * cfg.n_steps), progress=False,
                          overlap=cfg.overlap, **threads)


def bench_env(cfg: Config, tcfg: teacher.Config, nthread: int | None = None) -> float:
    """Env transitions per second of the batched core alone (uniform random actions, done envs reset), on
    ``nthread`` MuJoCo threads (default: the config's)."""
    nthread = nthread or cfg.nthread or None
    env = RotateCupVec(tcfg.env_config(), num_envs=cfg.num_envs, seed=cfg.seed, nthread=nthread)
    try:
        return random_steps_per_s(env, cfg.env_steps, cfg.seed)
    finally:
        env.close()


def bench_train(cfg: Config, tcfg: teacher.Config) -> tuple[float, int, dict[str, float]]:
    """Env transitions per second during PPO training (rollouts + updates), the number timed, and the update's
    and the rollout inference's own costs (:func:`time_costs`)."""
    torch.set_num_threads(tcfg.torch_threads)
    torch.manual_seed(cfg.seed)
    env = RotateCupSB3VecEnv(tcfg.env_config(), cfg.num_envs, seed=cfg.seed, nthread=cfg.nthread or None,
                             reward_scale=tcfg.reward_scale, obs_groups=TEACHER_GROUPS)
    model = ppo.build_model(tcfg, env)
    rollout = cfg.num_envs * cfg.n_steps
    total = max(1, -(-cfg.train_steps // rollout)) * rollout
    start = time.perf_counter()
    model.learn(total, progress_bar=False)
    wall = time.perf_counter() - start
    costs = time_costs(model)
    env.close()
    return model.num_timesteps / wall, int(model.num_timesteps), costs


def time_costs(model, repeats: int = 2) -> dict[str, float]:
    """Seconds of one PPO update on the last rollout, and of the policy's inference over one rollout, each alone
    (median of ``repeats``; the model's weights change, so call it once training is timed)."""
    from stable_baselines3.common.utils import obs_as_tensor

    model.overlap = False  # the update alone, with no rollout started beside it
    updates, inferences = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        model.train()
        updates.append(time.perf_counter() - start)
        obs = obs_as_tensor(model._last_obs, model.device)
        start = time.perf_counter()
        with torch.no_grad():
            for _ in range(model.n_steps):
                model.policy(obs)
        inferences.append(time.perf_counter() - start)
    return {"update_s": statistics.median(updates), "inference_s": statistics.median(inferences)}


def ceiling(rollout_physics_s: float, physics_core_s: float, cores: int, update_s: float,
            inference_s: float) -> float:
    """The highest train_over_env a recipe can reach on ``cores`` cores (module docstring)."""
    return min(1.0, cores * rollout_physics_s / (physics_core_s + update_s + inference_s))


def run(cfg: Config) -> dict:
    """Both measurements; prints a short summary and, last, the JSON result (also returned)."""
    if min(cfg.num_envs, cfg.env_steps, cfg.train_steps, cfg.n_steps, cfg.batch_size, cfg.n_epochs) < 1:
        raise ValueError("num_envs, env_steps, train_steps, n_steps, batch_size and n_epochs must all be >= 1")
    with tempfile.TemporaryDirectory() as tmp:  # PPO's TensorBoard files are not part of the result
        tcfg = teacher_config(cfg, Path(tmp))
        env_sps = bench_env(cfg, tcfg)
        env_sps_1 = bench_env(cfg, tcfg, nthread=1)
        train_sps, timed, costs = bench_train(cfg, tcfg)
    rollout = cfg.num_envs * cfg.n_steps
    rollout_physics_s, physics_core_s = rollout / env_sps, rollout / env_sps_1
    cores = num_cores()
    result = {
        "num_envs": cfg.num_envs,
        "overlap": cfg.overlap,
        "torch_threads": tcfg.torch_threads,
        "env_steps_per_s": round(env_sps, 1),
        "train_steps_per_s": round(train_sps, 1),
        "train_steps_timed": timed,
        "env_steps_per_s_1thread": round(env_sps_1, 1),
        "rollout_physics_s": round(rollout_physics_s, 3),
        "physics_core_s": round(physics_core_s, 3),
        "update_s": round(costs["update_s"], 3),
        "inference_s": round(costs["inference_s"], 3),
        "cores": cores,
        "train_over_env_ceiling": round(ceiling(rollout_physics_s, physics_core_s, cores, **costs), 4),
        "train_over_env": round(train_sps / env_sps, 4),
    }
    print(f"batched env alone: {env_sps:,.0f} steps/s; PPO training: {train_sps:,.0f} steps/s "
          f"({100 * train_sps / env_sps:.0f}% of the env alone)")
    print(f"per rollout of {rollout} steps: physics {result['physics_core_s']:.2f} core-s, one update "
          f"{result['update_s']:.2f} s, inference {result['inference_s']:.2f} s on {cores} cores -> no scheduling "
          f"of this recipe passes train_over_env {result['train_over_env_ceiling']:.2f} on this machine")
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
