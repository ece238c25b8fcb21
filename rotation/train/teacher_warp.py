"""The teacher on the MuJoCo Warp backend: PPO with rollouts, advantages and minibatches resident on the device
(`rotate train-teacher --backend warp`).

The learner is rsl_rl's PPO (`rsl-rl-lib`, the [warp] extra): its rollout storage, GAE, clipped surrogate,
clipped value loss and adaptive-KL learning rate, on tensors that never leave the GPU. The networks are this
project's: the actor is rotation.policy.actor.ActorNet (normalized proprio + EnvFactorEncoder(priv) -> 512-256-128
ELU -> action mean) with a state-independent log std, as in the CPU teacher; the critic is the same extractor and
MLP with a value head. So the run ends in the same policy bundle (`bundle/`), which `rotate evaluate` and deploy
load exactly like one trained by stable-baselines3, with the same TensorBoard tags (`episode/*`, `train/*`) and
`curves.jsonl` rows. docs/warp.md says why rsl_rl and what differs from the CPU learner.

    rotate train-teacher --backend warp --hand digit360 --out runs/teacher_gpu   # teacher_config.GPU_RECIPE by default
    rotate train-teacher --backend warp --hand digit360 --device cpu --num-envs 8 ...   # Warp's CPU device (tests)
    rotate train-teacher --backend warp --out runs/teacher_gpu --resume runs/teacher_gpu/checkpoints/last.pt
    rotate train-teacher --backend warp --hand digit360 --out runs/teacher_gpu2 --init-from runs/teacher/bundle

The warp backend does not simulate the physics of the vendor-kinematics hands yet (the default digit360_v4, and
xela_v4: rotation.sim_warp.core.physics_problem), so a warp run names the first hand model (`--hand digit360` or
`xela`) and warm-starts from a bundle trained on it; the config refuses any other in one line.

`--resume` continues a run from `checkpoints/last.pt` (actor, critic, optimizer, learning rate, step count) with the
same options but its length and speed; the worlds restart from fresh resets seeded with seed + steps, as on the cpu
backend. `--init-from BUNDLE` copies a teacher bundle's acting path (from either backend) into a fresh run; the fresh
critic trains alone for `--critic-warmup` updates, with the learning rate held, before the actor moves.
"""

from __future__ import annotations

import dataclasses
import json
import math
import signal
import time
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from envs.config import EnvConfig
from envs.errors import RequestRefused
from envs.metrics import UPRIGHT_TILT
from rotation.configs import to_jsonable
from rotation.interrupt import SIGNAL_NAMES, Interrupted, StopSignals
from rotation.policy.actor import ActorNet
from rotation.policy.bundle import PolicyBundle, load_policy_bundle
from rotation.runs import (
    GRASPS_KEY,
    CurveLog,
    DamagedCheckpoint,
    check_resume_record,
    run_record,
    save_atomically,
    summary_writer,
)
from rotation.train.teacher_config import TEACHER_GROUPS
from rotation.train.warp_models import build_models

# --------------------------------------------------------------------------------------------------------------------
# episode statistics on the device


class DeviceEpisodeStats:
    """Per-world running sums of the episode in progress and totals over the episodes that ended since the last
    :meth:`collect`, all tensors on the device (one host read per log point). Rows match the CPU teacher's
    EpisodeStats: return `r`, length `l`, rotation, rotation_rate, ttf, upright, and each `rew_<term>`."""

    def __init__(self, n: int, env_cfg: EnvConfig, device: torch.device) -> None:
        self.cfg = env_cfg
        self.dev = device
        self.ep: dict[str, torch.Tensor] = {}
        self.totals: dict[str, torch.Tensor] = {}
        self.n = n

    def _zeros(self) -> torch.Tensor:
        return torch.zeros(self.n, dtype=torch.float64, device=self.dev)

    def step(self, reward: torch.Tensor, terminated: torch.Tensor, truncated: torch.Tensor, info: dict) -> None:
        add = {"r": reward, "rotation": info["rotation"],
               "upright": ((info["tilt"] < UPRIGHT_TILT) & ~info["fell"]),
               **{k: v for k, v in info.items() if k.startswith("rew_")}}
        for k, v in add.items():
            self.ep[k] = self.ep.get(k, self._zeros()) + v.to(torch.float64)
        done = terminated | truncated
        steps = info["elapsed_steps"].to(torch.float64)
        ended = {
            "count": done.to(torch.float64),
            "r": self.ep["r"], "l": steps, "rotation": self.ep["rotation"],
            "rotation_rate": self.ep["rotation"] / (steps * self.cfg.control_dt),
            "ttf": torch.where(terminated, steps / self.cfg.episode_steps, 1.0),
            "upright": self.ep["upright"] / steps,
            **{k: v for k, v in self.ep.items() if k.startswith("rew_")},
        }
        for k, v in ended.items():
            self.totals[k] = self.totals.get(k, torch.zeros((), dtype=torch.float64, device=self.dev)) + \
                torch.where(done, v, 0.0).sum()
        for k in self.ep:
            self.ep[k] = torch.where(done, 0.0, self.ep[k])

    def collect(self) -> dict[str, float]:
        """Means over the episodes that ended since the last call ({} when none did), and a fresh start."""
        totals = {k: float(v) for k, v in self.totals.items()}  # one host read
        self.totals = {}
        count = totals.pop("count", 0.0)
        if count <= 0:
            return {}
        return {"episodes": int(count), **{k: v / count for k, v in totals.items()}}


# --------------------------------------------------------------------------------------------------------------------
# training


def _require_rsl_rl():
    try:
        from rsl_rl.algorithms import PPO
        from rsl_rl.storage import RolloutStorage
        from tensordict import TensorDict
    except ImportError as err:
        raise ValueError(f"the warp backend trains with rsl_rl ({err.name} is not installed): "
                         "pip install 'tactile-rotation[warp]'") from None
    return PPO, RolloutStorage, TensorDict


class WarpPPO:
    """rsl_rl's PPO wired to a RotateCupWarp: :meth:`iteration` collects one rollout of ``n_steps`` x ``num_envs``
    transitions on the device and updates on it (also what scripts/bench_warp.py times)."""

    def __init__(self, cfg, env, env_cfg: EnvConfig) -> None:
        ppo_cls, storage_cls, self._tensordict = _require_rsl_rl()
        n, horizon = env.num_envs, cfg.n_steps
        if (n * horizon) % cfg.batch_size:
            raise ValueError(f"batch_size {cfg.batch_size} must divide num_envs x n_steps = {n * horizon} on the "
                             "warp backend (rsl_rl splits each rollout into equal minibatches)")
        self.cfg, self.env, self.n, self.horizon = cfg, env, n, horizon
        self.config, self.actor, self.critic = build_models(cfg, env_cfg)
        dev = env.torch_device
        self.obs = self._td(env.reset(seed=cfg.seed))
        storage = storage_cls("rl", n, horizon, self.obs, [env.single_action_space.shape[0]], device=str(dev))
        self.alg = ppo_cls(self.actor, self.critic, storage, num_learning_epochs=cfg.n_epochs,
                           num_mini_batches=n * horizon // cfg.batch_size, clip_param=cfg.clip_range,
                           gamma=cfg.gamma, lam=cfg.gae_lambda, value_loss_coef=cfg.vf_coef,
                           entropy_coef=cfg.ent_coef, learning_rate=cfg.learning_rate,
                           max_grad_norm=cfg.max_grad_norm, schedule="adaptive", desired_kl=cfg.target_kl,
                           device=str(dev))
        self.stats = DeviceEpisodeStats(n, env_cfg, dev)

    def _td(self, obs: dict[str, torch.Tensor]):
        return self._tensordict({k: obs[k] for k in TEACHER_GROUPS}, batch_size=[self.n], device=self.env.torch_device)

    def iteration(self) -> dict[str, float]:
        """One rollout (every tensor stays on the device) and one PPO update; returns rsl_rl's mean losses."""
        alg, env = self.alg, self.env
        alg.train_mode()
        with torch.no_grad():
            for _ in range(self.horizon):
                actions = alg.act(self.obs)
                _, reward, terminated, truncated, info = env.step(actions)
                self.stats.step(reward, terminated, truncated, info)
                done = terminated | truncated
                env.reset_done(done)  # finished worlds restart on the device
                self.obs = self._td(env._observe())
                alg.process_env_step(self.obs, reward * self.cfg.reward_scale, done,
                                     {"time_outs": (truncated & ~terminated).to(torch.float32)})
            alg.compute_returns(self.obs)
        return alg.update()

    def critic_only(self) -> dict[str, float]:
        """One iteration that trains only the critic: the actor's weights, log std and normalization stay, and so
        does the learning rate (the adaptive rule would read the actor's zero KL as a reason to raise it)."""
        actor = self.alg.actor
        params = [p for p in actor.parameters() if p.requires_grad]
        lr = self.alg.learning_rate
        for p in params:
            p.requires_grad_(False)
        actor.learn_normalization = False
        try:
            return self.iteration()
        finally:
            for p in params:
                p.requires_grad_(True)
            actor.learn_normalization = True
            self.alg.learning_rate = lr
            for group in self.alg.optimizer.param_groups:
                group["lr"] = lr

    def load_state(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint's actor, critic, optimizer and learning rate."""
        try:
            self.alg.actor.load_state_dict(state["actor"])
            self.alg.critic.load_state_dict(state["critic"])
            self.alg.optimizer.load_state_dict(state["optimizer"])
        except (RuntimeError, ValueError, KeyError) as err:
            raise ValueError(f"the checkpoint's networks do not fit this run's (--net-arch {list(self.cfg.net_arch)}):"
                             f" {str(err).splitlines()[0]}") from None
        self.alg.learning_rate = float(state["learning_rate"])
        for group in self.alg.optimizer.param_groups:
            group["lr"] = self.alg.learning_rate

    def init_actor(self, bundle: PolicyBundle) -> None:
        """Copy a teacher bundle's acting path (normalization, encoder, actor MLP, action head) into the actor."""
        dev = self.env.torch_device
        try:
            self.actor.net.load_state_dict({k: v.to(dev) for k, v in bundle.net.state_dict().items()})
        except RuntimeError as err:
            raise ValueError(f"--init-from: the bundle's networks do not fit this run's (--net-arch "
                             f"{list(self.cfg.net_arch)}): {str(err).splitlines()[0]}") from None
        # the critic's proprio statistics start from the bundle's too (they are fixed in the critic)
        self.critic.extractor.proprio_norm.load_state_dict(bundle.net.extractor.proprio_norm.state_dict())

    def bundle(self, card: dict[str, Any]) -> PolicyBundle:
        """The acting path as a policy bundle on the CPU (the format the CPU teacher writes)."""
        bundle = PolicyBundle(dataclasses.replace(self.config, card=card), ActorNet(self.config))
        bundle.net.load_state_dict({k: v.detach().cpu() for k, v in self.actor.net.state_dict().items()})
        return bundle


def train(cfg) -> PolicyBundle:
    """Train the teacher on the Warp backend (cfg: rotation.train.teacher.Config with backend 'warp')."""
    from rotation.configs import save_config
    from rotation.runs import check_run_dir, clear_outputs
    from rotation.sim_warp.core import RotateCupWarp, WarpConfig
    from rotation.train.teacher_config import RESUMABLE_CHANGES, RUN_OUTPUTS

    _require_rsl_rl()
    out = cfg.out
    resume_dir = None
    if cfg.resume is not None:
        resume_dir = cfg.resume.parent.parent if cfg.resume.parent.name == "checkpoints" else None
    resuming_here = resume_dir is not None and resume_dir.resolve() == out.resolve()
    check_run_dir(out, RUN_OUTPUTS, overwrite=cfg.overwrite, resuming_here=resuming_here,
                  resume_hint=f"pass --resume {out / 'checkpoints' / 'last.pt'} to continue it")
    n, horizon = cfg.num_envs, cfg.n_steps
    if (n * horizon) % cfg.batch_size:
        raise ValueError(f"batch_size {cfg.batch_size} must divide num_envs x n_steps = {n * horizon} on the warp "
                         "backend (rsl_rl splits each rollout into equal minibatches)")
    state, init = None, None
    record = run_record(cfg)
    if cfg.resume is not None:
        saved = resume_dir / "config.json" if resume_dir is not None else None
        if saved is not None and saved.is_file():
            check_resume_record(json.loads(saved.read_text()), record, str(saved), RESUMABLE_CHANGES)
        state = load_checkpoint(cfg.resume)
    if cfg.init_from is not None:
        init = load_policy_bundle(cfg.init_from).require("privileged", f"--init-from {cfg.init_from}")
    steps = int(state["steps"]) if state is not None else 0
    torch.manual_seed(cfg.seed + steps)
    env_cfg = cfg.env_config()
    # a resumed run's worlds restart from fresh, reproducible resets (as the cpu backend's do)
    env = RotateCupWarp(env_cfg, n, seed=cfg.seed + steps, warp_cfg=WarpConfig(device=cfg.device))
    learner = WarpPPO(cfg, env, env_cfg)
    warmup = 0
    if state is not None:
        learner.load_state(state)
    elif init is not None:
        learner.init_actor(init)
        warmup = cfg.critic_warmup
    # every check passed: only now is anything in `out` written or deleted
    if cfg.overwrite and not resuming_here:
        removed = clear_outputs(out, RUN_OUTPUTS)
        if removed:
            print(f"teacher: --overwrite deleted {', '.join(removed)} in {out}")
    out.mkdir(parents=True, exist_ok=True)
    save_config(record, out / "config.json")
    curves = CurveLog(out / "curves.jsonl")
    if resuming_here and (dropped := curves.trim(steps)):
        print(f"teacher: dropped {dropped} curve rows logged after step {steps} (not in the checkpoint resumed from)")
    writer = summary_writer(out / "tb" / "teacher_1", purge_step=steps)
    iterations = max(0, math.ceil((cfg.total_steps - steps) / (n * horizon)))
    next_ckpt, rows, signum = (steps // cfg.checkpoint_every + 1) * cfg.checkpoint_every, [], None
    bar = tqdm(total=cfg.total_steps, initial=steps, unit="step", disable=not cfg.progress,
               desc="train-teacher (warp)", dynamic_ncols=True)
    start = time.time()
    t_iter = time.perf_counter()
    try:
        with StopSignals() as stop:
            for _ in range(iterations):
                if warmup > 0:
                    losses = learner.critic_only()
                    warmup -= 1
                else:
                    losses = learner.iteration()
                steps += n * horizon
                bar.update(n * horizon)
                now = time.perf_counter()
                row = _log(writer, steps, learner.stats.collect(), losses, learner.alg.learning_rate,
                           n * horizon / (now - t_iter))
                t_iter = now
                if row is not None:
                    rows.append(row)
                if steps >= next_ckpt:
                    _save_checkpoint(out, learner.alg, steps)
                    curves.append(rows)
                    rows = []
                    next_ckpt += cfg.checkpoint_every
                if stop.requested:
                    break
            signum = stop.signum
    except KeyboardInterrupt as err:
        signum = getattr(err, "signum", signal.SIGINT)
    finally:
        bar.close()
        writer.close()
        env.close()
    wall = time.time() - start
    _save_checkpoint(out, learner.alg, steps)
    curves.append(rows)
    card = {"role": "teacher", "object": cfg.object, "steps": steps, "seed": cfg.seed, "wall_time_s": round(wall, 1),
            "backend": "warp", "learner": "rsl_rl PPO (rotation.train.teacher_warp)",
            "train_config": to_jsonable(cfg),
            GRASPS_KEY: record[GRASPS_KEY]}
    if state is not None:
        card["resumed_from"] = str(cfg.resume)
    if init is not None:
        card["init_from"] = str(cfg.init_from)
    if signum:
        card["interrupted"] = f"stopped by {SIGNAL_NAMES.get(signum, signum)} at {steps} of {cfg.total_steps} steps"
    bundle = learner.bundle(card)
    bundle.save(out / "bundle")
    if signum:
        message = (f"teacher: interrupted by {SIGNAL_NAMES.get(signum, signum)} at {steps} of {cfg.total_steps} "
                   f"steps; saved the bundle {out / 'bundle'}; continue with --resume "
                   f"{out / 'checkpoints' / 'last.pt'}")
        print(message)
        raise Interrupted(signum, message)
    print(f"teacher: {steps} steps in {wall:.0f} s ({steps / max(wall, 1e-9):,.0f} steps/s) on the warp backend; "
          f"bundle at {out / 'bundle'}")
    return bundle


def _log(writer, steps: int, episodes: dict[str, float], losses: dict[str, float], lr: float,
         fps: float) -> dict[str, Any] | None:
    """TensorBoard points under the CPU teacher's tags; the curve row when episodes ended."""
    writer.add_scalar("train/value_loss", losses.get("value", float("nan")), steps)
    writer.add_scalar("train/policy_gradient_loss", losses.get("surrogate", float("nan")), steps)
    writer.add_scalar("train/entropy_loss", -losses.get("entropy", float("nan")), steps)
    writer.add_scalar("train/adaptive_lr", lr, steps)
    writer.add_scalar("time/fps", fps, steps)
    if not episodes:
        return None
    for k, v in episodes.items():
        if k != "episodes":
            writer.add_scalar(f"episode/{ {'r': 'return', 'l': 'length'}.get(k, k) }", v, steps)
    return {"steps": steps, **episodes}


CHECKPOINT_KEYS = ("actor", "critic", "optimizer", "learning_rate", "steps")


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A warp-backend checkpoint (`checkpoints/last.pt`), checked: DamagedCheckpoint for a file that cannot be read,
    ValueError for one of another program (a CPU run's .zip, say)."""
    path = Path(path)
    if not path.is_file():
        raise RequestRefused(f"--resume {path}: no such checkpoint"
                             + (" (a directory; give checkpoints/last.pt)" if path.is_dir() else ""))
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # pickle, zip and torch errors of a truncated or foreign file
        raise DamagedCheckpoint(f"--resume {path} cannot be read as a warp-backend checkpoint "
                                f"({type(err).__name__}); a cpu-backend run resumes from its .zip") from None
    if not isinstance(state, dict) or not set(CHECKPOINT_KEYS) <= set(state):
        raise ValueError(f"--resume {path} is not a warp-backend checkpoint (expected the entries "
                         f"{list(CHECKPOINT_KEYS)})")
    return state


def _save_checkpoint(out: Path, alg, steps: int) -> Path:
    """`checkpoints/last.pt`: actor, critic, optimizer, learning rate and steps (what --resume continues from),
    written atomically."""
    path = out / "checkpoints" / "last.pt"
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"actor": alg.actor.state_dict(), "critic": alg.critic.state_dict(),
             "optimizer": alg.optimizer.state_dict(), "learning_rate": alg.learning_rate, "steps": steps}
    save_atomically(lambda tmp: torch.save(state, tmp), path)
    return path


__all__ = ["WarpPPO", "train"]
