"""The CPU learner of the teacher and of a student fine-tune: stable-baselines3 PPO with an adaptive-KL learning
rate and the rollout overlap, its callbacks (episode statistics, checkpoints) and how its checkpoints load,
resume and become bundles.
"""

from __future__ import annotations

import json
import time
import warnings
import zipfile
import zlib
from pathlib import Path

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

from envs.errors import RequestRefused
from rotation.configs import to_jsonable
from rotation.interrupt import StopSignals
from rotation.policy.bundle import PolicyBundle, load_policy_bundle
from rotation.policy.features import (
    LatentMixExtractor,
    PrivilegedExtractor,
    StudentExtractor,
    StudentPPOPolicy,
    policy_kwargs,
)
from rotation.policy.networks import EnvFactorEncoderConfig, RunningNorm
from rotation.runs import (
    CurveLog,
    DamagedCheckpoint,
    remove_owner,
    save_atomically,
    write_owner,
)
from rotation.train.overlap import RolloutPrefetch
from rotation.train.teacher_config import Config
from rotation.train.vec_env import RotateCupSB3VecEnv


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


class AdaptiveKLPPO(RolloutPrefetch, PPO):
    """PPO whose learning rate follows the adaptive-KL rule after every update (rl_games / Hora), optionally with
    the next rollout collected during the update (``overlap``; rotation.train.overlap)."""

    def _setup_model(self) -> None:
        # a loaded model already holds its schedule (the current rate and the target), which SB3's setup would
        # replace with a constant one at the starting rate: keep it, so a resume continues the schedule exactly
        loaded = getattr(self, "lr_schedule", None)
        super()._setup_model()
        fresh = not isinstance(loaded, KLSchedule)
        self.lr_schedule = KLSchedule(float(self.learning_rate), Config.target_kl) if fresh else loaded

    critic_warmup: int = 0
    """Updates left that train only the critic (after --init-from: a fresh critic's first value estimates would
    otherwise steer the copied actor with noise)."""

    def train(self) -> None:
        if self.critic_warmup > 0:
            self._train_critic_only()
            return
        super().train()
        kl = self.logger.name_to_value.get("train/approx_kl")
        if kl is not None and np.isfinite(kl):
            # with overlap the KL is taken from the policy that acted, one update back (lag + this update): the
            # schedule judges both together, which keeps each update inside the trust region the target sets
            self.lr_schedule.update(float(kl))
        self.logger.record("train/adaptive_lr", self.lr_schedule.lr)

    def _train_critic_only(self) -> None:
        critic = ("mlp_extractor.value_net.", "value_net.", "vf_features_extractor.")
        frozen = [p for n, p in self.policy.named_parameters() if not n.startswith(critic) and p.requires_grad]
        norms = [m for m in self.policy.modules() if isinstance(m, RunningNorm) and not m.frozen]
        for p in frozen:
            p.requires_grad_(False)
        try:
            for m in norms:  # the actor's input statistics stay as they were too
                m.frozen = True
            super().train()  # the schedule is left alone: the actor did not move
        finally:
            for p in frozen:
                p.requires_grad_(True)
            for m in norms:
                m.frozen = False
        self.critic_warmup -= 1
        self.logger.record("train/critic_warmup_left", self.critic_warmup)


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
    """Saves `step_<n>.zip` every `every` steps and `last.zip` (keeps the newest two numbered ones), each written
    atomically, and appends the curve rows logged since the last one to `curves` (flushed to disk). Stops training
    (returns False) once ``stop`` saw a signal.

    Every checkpoint carries the run's training wall time so far (``model.train_wall_s``: ``wall_before``, the
    earlier legs' time read from the checkpoint resumed, plus this leg's; None where an earlier leg's is unknown)."""

    def __init__(self, folder: Path, every: int, stats: EpisodeStats | None = None, curves: CurveLog | None = None,
                 stop: StopSignals | None = None, owner: str | None = None, wall_before: float | None = 0.0) -> None:
        super().__init__()
        self.folder, self.every, self.owner = folder, every, owner
        self.stats, self.curves, self.stop = stats, curves, stop
        self.flushed = 0  # rows of stats.history already in curves
        self.next_at = 0
        self.wall_before, self.started = wall_before, time.time()

    def run_wall_s(self) -> float | None:
        """The run's training wall time up to now, over every leg (None where an earlier leg's is unknown)."""
        return None if self.wall_before is None else self.wall_before + time.time() - self.started

    def _on_training_start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        self.next_at = (self.num_timesteps // self.every + 1) * self.every

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.next_at:
            self.save()
            self.next_at += self.every
        return not (self.stop is not None and self.stop.requested)

    def save(self) -> Path:
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / f"step_{self.num_timesteps:010d}.zip"
        self.model.train_wall_s = self.run_wall_s()  # saved with the model's other attributes
        save_atomically(self.model.save, path)
        write_owner(path, self.owner)  # the run that wrote it (rotation.runs)
        save_atomically(self.model.save, self.folder / "last.zip")
        write_owner(self.folder / "last.zip", self.owner)
        for old in sorted(self.folder.glob("step_*.zip"))[:-2]:
            old.unlink()
            remove_owner(old)
        if self.stats is not None and self.curves is not None:
            self.curves.append(self.stats.history[self.flushed :])
            self.flushed = len(self.stats.history)
        return path


def load_checkpoint(path: str | Path, env: RotateCupSB3VecEnv | None = None, device: str = "cpu") -> AdaptiveKLPPO:
    """A train-teacher checkpoint (.zip). Raises DamagedCheckpoint for a file that cannot be read back (truncated,
    corrupted) and ValueError for one of another program, policy or observation space."""
    path = Path(path)
    if not path.is_file():
        raise RequestRefused(f"no such checkpoint: {path}"
                             + (" (a directory; give a .zip file)" if path.is_dir() else ""))
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            broken = archive.testzip()  # reads every member and checks its CRC
    except (zipfile.BadZipFile, OSError, EOFError, zlib.error) as err:
        raise DamagedCheckpoint(f"{path} is not a readable zip file ({type(err).__name__}: {err})") from None
    if broken is not None:
        raise DamagedCheckpoint(f"{path}: member {broken!r} is corrupted")
    if not {"data", "policy.pth"} <= set(names):
        raise ValueError(f"{path} is not a train-teacher checkpoint: a zip of {sorted(names)[:6]}, not a "
                         "stable-baselines3 model ('data', 'policy.pth')")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # SB3 warns about version differences; a mismatch fails below
            model = AdaptiveKLPPO.load(path, env=env, device=device)
    except Exception as err:  # SB3 raises many kinds (ValueError for other spaces, KeyError, pickle errors)
        raise ValueError(f"{path} cannot be loaded as a train-teacher checkpoint ({type(err).__name__}: "
                         f"{str(err).splitlines()[0] if str(err) else ''})") from None
    extractor = getattr(model.policy, "features_extractor", None)
    if not (isinstance(extractor, PrivilegedExtractor)
            or (isinstance(model.policy, StudentPPOPolicy) and isinstance(extractor, StudentExtractor))):
        raise ValueError(f"{path} holds a {type(model.policy).__name__} with a {type(extractor).__name__} features "
                         "extractor, not the teacher's privileged policy (PrivilegedExtractor) or a student "
                         "fine-tune (StudentPPOPolicy)")
    return model


def older_checkpoints(path: Path) -> list[Path]:
    """The numbered checkpoints beside ``path`` that precede it, newest first (all of them for last.zip)."""
    steps = sorted(path.parent.glob("step_*.zip"), reverse=True)
    if path.name.startswith("step_"):
        steps = [p for p in steps if p.name < path.name]
    return [p for p in steps if p != path]


def checkpoint_options(model: AdaptiveKLPPO) -> dict:
    """The PPO options a checkpoint was trained with, in Config's names and JSON form."""
    arch = model.policy_kwargs.get("net_arch", {})
    arch = arch.get("pi") if isinstance(arch, dict) else arch
    schedule = model.lr_schedule
    return to_jsonable({
        "num_envs": model.n_envs, "n_steps": model.n_steps, "batch_size": model.batch_size,
        "n_epochs": model.n_epochs, "learning_rate": float(model.learning_rate),
        "target_kl": schedule.target if isinstance(schedule, KLSchedule) else None, "gamma": model.gamma,
        "gae_lambda": model.gae_lambda, "clip_range": float(model.clip_range(1.0)), "vf_coef": model.vf_coef,
        "ent_coef": model.ent_coef, "max_grad_norm": model.max_grad_norm, "net_arch": list(arch or []),
        "log_std_init": model.policy_kwargs.get("log_std_init"),
    })


def bundle_from_checkpoint(path: str | Path, card: dict | None = None) -> PolicyBundle:
    """The policy bundle of a training checkpoint (.zip), e.g. to evaluate or ship a run that is still going."""
    path = Path(path)
    if not path.is_file():
        raise RequestRefused(f"no such checkpoint: {path}")
    model = load_checkpoint(path)
    run_cfg = path.parent.parent / "config.json"
    train_config = json.loads(run_cfg.read_text()) if run_cfg.is_file() else {}
    role = "student" if isinstance(model.policy, StudentPPOPolicy) else "teacher"
    info = {"role": role, "object": train_config.get("object", "cup"), "steps": int(model.num_timesteps),
            "seed": train_config.get("seed"), "checkpoint": path.name, "train_config": train_config}
    if train_config.get("student"):  # a student fine-tune: what it started from, as the run's own bundle records it
        info["finetuned_from"] = {"bundle": train_config["student"],
                                  "card": load_policy_bundle(train_config["student"]).config.card}
    return PolicyBundle.from_sb3(model, card=info | (card or {}))


def build_model(cfg: Config, env: RotateCupSB3VecEnv) -> AdaptiveKLPPO:
    if cfg.resume is not None:
        if not Path(cfg.resume).is_file():
            raise RequestRefused(f"--resume {cfg.resume}: no such checkpoint")
        return AdaptiveKLPPO.load(cfg.resume, env=env, device=cfg.device)
    if cfg.student:
        return build_student_model(cfg, env)
    model = _new_ppo(cfg, env, "MultiInputPolicy", policy_kwargs())
    model.overlap = cfg.overlap
    if cfg.init_from is not None:
        init_actor(model, cfg.init_from)
        model.critic_warmup = cfg.critic_warmup
    return model


def _new_ppo(cfg: Config, env: RotateCupSB3VecEnv, policy: str | type, kwargs: dict) -> AdaptiveKLPPO:
    """A fresh AdaptiveKLPPO with the run's PPO options; ``kwargs`` are the policy's, completed with the run's
    log std and actor/critic sizes."""
    kwargs = dict(kwargs, log_std_init=cfg.log_std_init, net_arch=dict(pi=list(cfg.net_arch), vf=list(cfg.net_arch)))
    model = AdaptiveKLPPO(
        policy, env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps, batch_size=cfg.batch_size,
        n_epochs=cfg.n_epochs, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_range=cfg.clip_range,
        ent_coef=cfg.ent_coef, vf_coef=cfg.vf_coef, max_grad_norm=cfg.max_grad_norm, policy_kwargs=kwargs,
        tensorboard_log=str(cfg.out / "tb"), seed=cfg.seed, device=cfg.device, verbose=0,
    )
    model.lr_schedule = KLSchedule(cfg.learning_rate, cfg.target_kl)
    return model


def build_student_model(cfg: Config, env: RotateCupSB3VecEnv) -> AdaptiveKLPPO:
    """PPO over a student bundle's acting path (StudentPPOPolicy): phi frozen, a fresh privileged critic that trains
    alone for ``critic_warmup`` updates first."""
    student = load_policy_bundle(cfg.student)
    scfg = student.config
    if list(scfg.actor_hidden) != list(cfg.net_arch):
        raise ValueError(f"net_arch {list(cfg.net_arch)} differs from the student's actor {list(scfg.actor_hidden)}; "
                         "give --net-arch " + " ".join(map(str, scfg.actor_hidden)))
    extractor_kwargs = dict(adaptation=scfg.adaptation, norm_clip=scfg.norm_clip)
    teacher = load_policy_bundle(cfg.latent_teacher) if cfg.latent_mix > 0 else None
    if teacher is not None:
        extractor_kwargs["teacher_encoder"] = teacher.net.extractor.encoder.cfg
    kwargs = dict(policy_kwargs(norm_clip=scfg.norm_clip),
                  features_extractor_class=LatentMixExtractor if teacher is not None else StudentExtractor,
                  features_extractor_kwargs=extractor_kwargs,
                  critic_encoder=EnvFactorEncoderConfig(latent_dim=scfg.latent_dim))
    model = _new_ppo(cfg, env, StudentPPOPolicy, kwargs)
    policy = model.policy
    state = student.net.extractor.state_dict()
    if teacher is not None:
        state |= {f"teacher_encoder.{k}": v for k, v in teacher.net.extractor.encoder.state_dict().items()}
    policy.pi_features_extractor.load_state_dict(state)
    policy.mlp_extractor.policy_net.load_state_dict(student.net.actor.state_dict())
    policy.action_net.load_state_dict(student.net.action_mean.state_dict())
    # the critic's proprio statistics start from the student's (they stay fixed while the critic warms up)
    policy.vf_features_extractor.proprio_norm.load_state_dict(student.net.extractor.proprio_norm.state_dict())
    model.critic_warmup = cfg.critic_warmup
    return model


def init_actor(model: AdaptiveKLPPO, path: Path) -> None:
    """Copy a teacher bundle's acting path (normalization, encoder, actor MLP, action head) into ``model``."""
    bundle = load_policy_bundle(path).require("privileged", f"--init-from {path}")
    policy = model.policy
    try:
        policy.features_extractor.load_state_dict(bundle.net.extractor.state_dict())
        policy.mlp_extractor.policy_net.load_state_dict(bundle.net.actor.state_dict())
        policy.action_net.load_state_dict(bundle.net.action_mean.state_dict())
    except RuntimeError as err:  # other layer sizes
        raise ValueError(f"--init-from {path}: the bundle's networks do not fit this run's (--net-arch "
                         f"{list(policy.mlp_extractor.policy_net)}): {str(err).splitlines()[0]}") from None
