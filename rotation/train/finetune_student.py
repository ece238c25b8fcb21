"""Fine-tune a distilled student's actor with PPO on its own latent estimate (`rotate finetune-student`).

Distillation teaches phi to estimate the teacher's z from 30 steps of joints, but the actor it feeds was trained on
the true z. Where phi cannot know z (the first 1.5 s of an episode, when the history is still mostly the start pose;
friction and mass that joints alone barely show) the student acts as confidently as the teacher would on a wrong
z, and drops the cup. Here PPO trains the student's actor on the latent it really gets: phi and its history
normalization stay frozen (the latent keeps the teacher's meaning, which the tactile adapter corrects toward), the
actor MLP, the action head, the actor's proprio normalization and the action std learn, and an asymmetric critic
reads the privileged groups (rotation.policy.features.StudentPPOPolicy). The fresh critic trains alone for
--critic-warmup updates before the actor moves.

    rotate finetune-student --student student --out runs/student_rl --total-steps 8000000
    rotate finetune-student --resume runs/student_rl/checkpoints/last.zip --total-steps 12000000

With --latent-mix P the actor also trains on latents it will meet beside a tactile adapter: in a share P of the
episodes its latent is moved from phi toward the teacher's z by a weight drawn uniformly in [0, 1]
(rotation.policy.features.LatentMixExtractor; the teacher's env-factor encoder is read from --latent-teacher and
stays out of the bundle). An actor fine-tuned on phi alone learns to act much the same whatever z says, which caps
what any latent correction can buy; mixed in, it learns to use z, at the price of trusting phi more when alone
(measured in experiments/adapter/tried_latent_mix).

Everything else works as in `rotate train-teacher` (the same PPO, checkpoints, curves, TensorBoard, --resume,
--overwrite, signals); the result in `out/bundle` is a student bundle (latent source 'adaptation') that evaluate,
view, collect and deploy load like any student.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from rotation.policy.bundle import PolicyBundle
from rotation.train import teacher, teacher_config


@dataclass
class Config(teacher_config.Config):
    """`rotate finetune-student`: train-teacher's options with the student set and a fine-tuning recipe."""

    out: Path = Path("runs/student_rl")
    """Output directory (checkpoints, TensorBoard logs, config, final student bundle)."""
    student: str = "student"
    """The distilled student bundle to fine-tune (directory or shipped name)."""
    num_envs: int = 512
    """Simulations stepped together in one process."""
    n_steps: int = 32
    """Horizon per env per PPO update (16,384 transitions per update with 512 envs)."""
    batch_size: int = 4096
    """PPO minibatch size."""
    n_epochs: int = 5
    """Passes over each rollout."""
    learning_rate: float = 3e-4
    """Starting learning rate of the adaptive-KL schedule (a trained actor: smaller steps than from scratch)."""
    log_std_init: float = -1.0
    """Initial log std of the Gaussian actions: std 0.37, narrower than from scratch, around a trained actor."""
    total_steps: int = 8_000_000
    """Total environment steps, counted across resumes."""
    backend: Literal["cpu"] = "cpu"
    """Physics backend: the cpu backend only (a student fine-tune runs stable-baselines3's PPO on its actor)."""
    overlap: bool = False
    """Collect the next rollout during the update (train-teacher's --overlap). Off by default here: around a trained
    actor with a narrow std the adaptive-KL schedule, which then judges the previous update's lag too, cut the
    learning rate to 2e-5 within 0.5 M steps and the fine-tune stalled (measured); plain PPO kept learning."""

    def __post_init__(self) -> None:
        if not self.student:
            raise ValueError("student: give the student bundle to fine-tune (a directory or a shipped name)")
        super().__post_init__()


def config_from_args(args) -> Config:
    """As train-teacher's: a --resume takes the run's options (the student bundle included) the command line
    leaves out."""
    return teacher_config._config_from_args(Config, args)


def run(cfg: Config) -> PolicyBundle:
    return teacher.run(cfg)
