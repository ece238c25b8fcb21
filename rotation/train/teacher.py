"""Train the privileged teacher with PPO on the batched env (`rotate train-teacher`).

The teacher sees the normalized proprioception (3 x 32) and a latent z = EnvFactorEncoder(priv) of the privileged
object properties; actor and critic are 512-256-128 ELU MLPs (reference/hora.md). Changes from Hora's GPU recipe,
for a 2-core CPU: 256 envs instead of 16,384 with a horizon of 16 instead of 8 (4,096 transitions per update
instead of 131,072); minibatches of 2,048 instead of 32,768; 3 epochs per update instead of 5 (the updates, not the
physics, bound the step rate on a CPU); a starting learning rate of 1e-3 instead of 5e-3 (smaller batches give
noisier gradients) with the same adaptive-KL schedule (target 0.02); rewards scaled by 0.1 without a value
normalizer (SB3 has none; Hora scaled by 0.01 and normalized values); initial action std 0.6 instead of 1; and in
the env a lighter pose penalty and a fall penalty (envs.config.RewardConfig says why).

    rotate train-teacher --out runs/teacher --total-steps 30000000
    rotate train-teacher --out runs/teacher --resume runs/teacher/checkpoints/last.zip --total-steps 40000000
    tensorboard --logdir runs/teacher/tb

Writes checkpoints (`checkpoints/step_*.zip`, `checkpoints/last.zip`), `config.json`, TensorBoard logs and the
final policy bundle `bundle/` (weights + config, what evaluation and deploy load).
"""

from __future__ import annotations

import dataclasses
import json
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList

from envs.config import EnvConfig, RandomizationConfig
from rotation.configs import save_config
from rotation.policy.bundle import PolicyBundle
from rotation.policy.features import policy_kwargs
from rotation.train.vec_env import RotateCupSB3VecEnv


@dataclass
class Config:
    out: Path = Path("runs/teacher")
    """Output directory (checkpoints, TensorBoard logs, config, final bundle)."""
    object: str = "cup"
    """Training object (envs.objects): the upright cup with a handle, scaled per env."""
    num_envs: int = 256
    """Simulations stepped together in one process."""
    total_steps: int = 30_000_000
    """Total environment steps (all envs together), counted across resumes."""
    seed: int = 0
    """Seed of the env streams and of torch."""
    n_steps: int = 16
    """Horizon per env per PPO update (transitions per update = num_envs x n_steps)."""
    batch_size: int = 2048
    """PPO minibatch size."""
    n_epochs: int = 3
    """Passes over each rollout (Hora: 5). On one CPU core the minibatch updates cost 2-3x the env stepping, so
    3 epochs buy more env steps per hour than 5 lose in sample efficiency."""
    learning_rate: float = 1e-3
    """Starting learning rate of the adaptive-KL schedule."""
    target_kl: float = 0.02
    """KL target of the adaptive schedule: lr / 1.5 above 2x, lr x 1.5 below 0.5x (Hora / rl_games)."""
    gamma: float = 0.99
    """Discount (Hora: 0.99)."""
    gae_lambda: float = 0.95
    """GAE lambda (Hora: 0.95)."""
    clip_range: float = 0.2
    """PPO ratio clip (Hora: 0.2)."""
    vf_coef: float = 1.0
    """Value loss weight."""
    ent_coef: float = 0.0
    """Entropy bonus (Hora: 0)."""
    max_grad_norm: float = 1.0
    """Gradient norm clip (Hora: 1.0)."""
    net_arch: tuple[int, ...] = (512, 256, 128)
    """Hidden layers of the actor and of the critic MLPs (ELU), Hora's sizes."""
    log_std_init: float = -0.5
    """Initial log standard deviation of the Gaussian actions (Hora: 0). std 0.6 instead of 1 explores with
    coherent finger motions instead of jitter that mostly earns penalties."""
    reward_scale: float = 0.1
    """Multiplies rewards seen by the learner (logged episode returns are unscaled)."""
    checkpoint_every: int = 1_000_000
    """Save a checkpoint every this many env steps."""
    resume: Path | None = None
    """Checkpoint (.zip) to continue from; the step count continues from it."""
    randomize: bool = True
    """Domain randomization on (Hora's ranges); off trains on nominal physics (an easy setting for tests)."""
    episode_steps: int = 400
    """Episode length in policy steps (20 s at 20 Hz)."""
    grasp_cache: str = ""
    """Grasp cache file; empty = the one shipped for the object."""
    torch_threads: int = 1
    """Threads for torch. 1 on a 2-core machine: torch's spinning workers starve MuJoCo's thread pool otherwise."""
    progress: bool = True
    """Show a progress bar."""
    device: str = "cpu"
    """Torch device for PPO ('cpu' is fastest for these small MLPs)."""

    def env_config(self) -> EnvConfig:
        rc = RandomizationConfig() if self.randomize else RandomizationConfig(enabled=False)
        return EnvConfig(object=self.object, episode_steps=self.episode_steps, randomization=rc,
                         grasp_cache=self.grasp_cache)


class KLSchedule:
    """A learning-rate 'schedule' holding the current rate, which the adaptive-KL rule moves (saved with the model)."""

    def __init__(self, lr: float, target: float) -> None:
        self.lr, self.target = lr, target

    def __call__(self, _progress_remaining: float) -> float:
        return self.lr

    def update(self, kl: float) -> None:
        """rl_games' rule: divide by 1.5 above 2x the target, multiply by 1.5 below half of it, within [1e-6, 1e-2]."""
        if kl > 2.0 * self.target:
            self.lr = max(self.lr / 1.5, 1e-6)
        elif kl < 0.5 * self.target:
            self.lr = min(self.lr * 1.5, 1e-2)


class AdaptiveKLPPO(PPO):
    """PPO whose learning rate follows the adaptive-KL rule after every update (rl_games / Hora)."""

    def _setup_model(self) -> None:
        super()._setup_model()
        if not isinstance(self.lr_schedule, KLSchedule):
            self.lr_schedule = KLSchedule(float(self.learning_rate), 0.02)

    def train(self) -> None:
        super().train()
        kl = self.logger.name_to_value.get("train/approx_kl")
        if kl is not None and np.isfinite(kl):
            self.lr_schedule.update(float(kl))
        self.logger.record("train/adaptive_lr", self.lr_schedule.lr)


class EpisodeStats(BaseCallback):
    """Logs per-episode statistics (return, length, rotation rate, time to fall, each reward term) to TensorBoard."""

    def __init__(self) -> None:
        super().__init__()
        self.episodes: list[dict] = []
        self.history: list[dict] = []

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            ep = info.get("episode")
            if ep is not None:
                self.episodes.append(ep)
        return True

    def _on_rollout_end(self) -> None:
        if not self.episodes:
            return
        keys = self.episodes[0].keys()
        means = {k: float(np.mean([e[k] for e in self.episodes])) for k in keys}
        for k, v in means.items():
            self.logger.record(f"episode/{ {'r': 'return', 'l': 'length'}.get(k, k) }", v)
        self.history.append({"steps": int(self.num_timesteps), "episodes": len(self.episodes), **means})
        self.episodes = []


class Checkpoints(BaseCallback):
    """Saves `step_<n>.zip` every `every` steps and `last.zip` (keeps the newest two numbered ones)."""

    def __init__(self, folder: Path, every: int) -> None:
        super().__init__()
        self.folder, self.every = folder, every
        self.next_at = 0

    def _on_training_start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        self.next_at = (self.num_timesteps // self.every + 1) * self.every

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next_at:
            self.save()
            self.next_at += self.every
        return True

    def save(self) -> Path:
        path = self.folder / f"step_{self.num_timesteps:010d}.zip"
        self.model.save(path)
        self.model.save(self.folder / "last.zip")
        for old in sorted(self.folder.glob("step_*.zip"))[:-2]:
            old.unlink()
        return path


def bundle_from_checkpoint(path: str | Path, card: dict | None = None) -> PolicyBundle:
    """The policy bundle of a training checkpoint (.zip), e.g. to evaluate or ship a run that is still going."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no such checkpoint: {path}")
    model = AdaptiveKLPPO.load(path, device="cpu")
    run_cfg = path.parent.parent / "config.json"
    train_config = json.loads(run_cfg.read_text()) if run_cfg.is_file() else {}
    info = {"role": "teacher", "object": train_config.get("object", "cup"), "steps": int(model.num_timesteps),
            "seed": train_config.get("seed"), "checkpoint": path.name, "train_config": train_config}
    return PolicyBundle.from_sb3(model, card=info | (card or {}))


def build_model(cfg: Config, env: RotateCupSB3VecEnv) -> AdaptiveKLPPO:
    if cfg.resume is not None:
        if not Path(cfg.resume).is_file():
            raise ValueError(f"--resume {cfg.resume}: no such checkpoint")
        return AdaptiveKLPPO.load(cfg.resume, env=env, device=cfg.device)
    model = AdaptiveKLPPO(
        "MultiInputPolicy", env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps, batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_range=cfg.clip_range,
        ent_coef=cfg.ent_coef, vf_coef=cfg.vf_coef, max_grad_norm=cfg.max_grad_norm,
        policy_kwargs=dict(policy_kwargs(), log_std_init=cfg.log_std_init,
                           net_arch=dict(pi=list(cfg.net_arch), vf=list(cfg.net_arch))),
        tensorboard_log=str(cfg.out / "tb"), seed=cfg.seed, device=cfg.device, verbose=0,
    )
    model.lr_schedule = KLSchedule(cfg.learning_rate, cfg.target_kl)
    return model


def _raise_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def run(cfg: Config) -> PolicyBundle:
    if cfg.total_steps < 1 or cfg.num_envs < 1:
        raise ValueError(f"total_steps and num_envs must be >= 1, got {cfg.total_steps}, {cfg.num_envs}")
    if cfg.batch_size > cfg.num_envs * cfg.n_steps:
        raise ValueError(f"batch_size {cfg.batch_size} exceeds the rollout size num_envs x n_steps = "
                         f"{cfg.num_envs * cfg.n_steps}")
    torch.set_num_threads(cfg.torch_threads)
    torch.manual_seed(cfg.seed)
    cfg.out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, cfg.out / "config.json")
    env_cfg = cfg.env_config()
    env = RotateCupSB3VecEnv(env_cfg, cfg.num_envs, seed=cfg.seed, reward_scale=cfg.reward_scale)
    model = build_model(cfg, env)
    if cfg.resume is not None:
        env.seed(cfg.seed + model.num_timesteps)  # fresh, reproducible episodes after a resume
    stats, ckpt = EpisodeStats(), Checkpoints(cfg.out / "checkpoints", cfg.checkpoint_every)
    remaining = cfg.total_steps - model.num_timesteps
    start = time.time()
    if remaining > 0:
        # Ctrl-C or SIGTERM stop training early; the checkpoint, curves and bundle below are still written
        previous = signal.signal(signal.SIGTERM, _raise_interrupt)
        try:
            model.learn(remaining, callback=CallbackList([stats, ckpt]), progress_bar=cfg.progress,
                        reset_num_timesteps=cfg.resume is None, tb_log_name="teacher")
        except KeyboardInterrupt:
            print(f"teacher: interrupted at {model.num_timesteps} steps; saving a checkpoint and the bundle")
        finally:
            signal.signal(signal.SIGTERM, previous)
    wall = time.time() - start
    ckpt.model = model
    ckpt.num_timesteps = model.num_timesteps
    ckpt.save()
    curves = cfg.out / "curves.jsonl"
    with curves.open("a") as f:
        for row in stats.history:
            f.write(json.dumps(row) + "\n")
    card = {"role": "teacher", "object": cfg.object, "steps": int(model.num_timesteps), "seed": cfg.seed,
            "wall_time_s": round(wall, 1), "train_config": dataclasses.asdict(cfg) | {"out": str(cfg.out),
                                                                                   "resume": str(cfg.resume)}}
    bundle = PolicyBundle.from_sb3(model, control_hz=env_cfg.control_hz, action_scale=env_cfg.action_scale, card=card)
    bundle.save(cfg.out / "bundle")
    env.close()
    print(f"teacher: {model.num_timesteps} steps in {wall:.0f} s; bundle at {cfg.out / 'bundle'}")
    return bundle
