"""Give a student a cautious start: its latent shifted toward slippery cups over its first control steps.

    python scripts/cautious_start.py --student student --teacher teacher --steps 20 --calibration-seed 11600000 \\
        --out runs/student_cautious

The student cannot tell a slippery cup from a nominal one before its joint history shows the cup slipping, and its
slippery cups fall in the first second (experiments/adapter/v4_stage11c: 55-59 of 128 at friction x0.25 within
2 s); the teacher, which knows, keeps them, and treating a nominal cup as a slippery one costs it nothing
measurable. This writes a copy of the student whose bundle adds, over its first ``--steps`` control steps of each
episode (each deploy run), a constant shift to its latent: the mean over ``--calibration-envs`` starts of the
training randomization (seeded ``--calibration-seed``) of the teacher's z with the cup's friction scaled by
``--friction-factor`` minus its z with the true friction. A constant vector: nothing privileged is read when it
acts, so a real hand runs it as the simulation does (`rotate evaluate`, `rotate deploy`, `rotate view` and `rotate
collect` apply it from each episode's first step; an adapter on this student adds its correction on top, though
`rotate finetune-adapter` trains it with the student acting without the shift).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from envs.config import EnvConfig, default_randomization
from envs.constants import PRIV_FIELDS
from envs.core import RotateCupVec
from envs.sim_identity import bundle_hand
from envs.validation import check_output_dir
from rotation.configs import script_main
from rotation.policy.bundle import PolicyBundle, resolve_bundle


@dataclass
class Config:
    student: str = "student"
    """Student bundle (a shipped name or a directory) that gets the cautious start."""
    teacher: str = "teacher"
    """Teacher bundle whose env-factor encoder gives the shift (the one the student was distilled from)."""
    steps: int = 20
    """Control steps from each episode's first over which the shift is added (20 = 1 s at 20 Hz)."""
    friction_factor: float = 0.25
    """The slippery cup the start assumes: the teacher's z at this factor of the true friction."""
    calibration_envs: int = 256
    """Starts of the training randomization the shift is averaged over."""
    calibration_seed: int = 11600000
    """Their seed (keep it apart from any evaluation's)."""
    out: Path = Path("runs/student_cautious")
    """Directory for the new student bundle (refused if it already holds one)."""

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if not (0.0 < self.friction_factor < 1.0):
            raise ValueError(f"friction_factor must be in (0, 1) (a more slippery cup), got {self.friction_factor}")
        if self.calibration_envs < 1:
            raise ValueError(f"calibration_envs must be >= 1, got {self.calibration_envs}")


def slippery_shift(teacher: PolicyBundle, hand: str, n: int, seed: int, factor: float) -> np.ndarray:
    """(Z,) mean over n starts of the teacher's z with the friction times ``factor`` minus its z."""
    env = RotateCupVec(EnvConfig(hand=hand, randomization=default_randomization(hand)), num_envs=n, seed=seed,
                       nthread=1)
    try:
        obs = env.reset(seed=seed)
    finally:
        env.close()
    groups = {key: obs[key] for key in teacher.config.obs_groups}
    slippery = {**groups, "priv": groups["priv"].copy()}
    slippery["priv"][:, PRIV_FIELDS.index("friction")] *= factor
    return (teacher.latent(slippery) - teacher.latent(groups)).mean(axis=0)


def run(cfg: Config) -> Path:
    if (cfg.out / "config.json").exists():
        raise ValueError(f"{cfg.out} already holds a bundle; give another --out or remove it")
    check_output_dir("--out", cfg.out)
    student = PolicyBundle.load(resolve_bundle(cfg.student)).require("adaptation", f"--student {cfg.student}")
    teacher = PolicyBundle.load(resolve_bundle(cfg.teacher)).require("privileged", f"--teacher {cfg.teacher}")
    if student.config.latent_dim != teacher.config.latent_dim:
        raise ValueError(f"the student's latent has {student.config.latent_dim} dimensions, the teacher's "
                         f"{teacher.config.latent_dim}: give the teacher it was distilled from")
    hand = bundle_hand(student.config.sim)
    shift = slippery_shift(teacher, hand, cfg.calibration_envs, cfg.calibration_seed, cfg.friction_factor)
    card = {**student.config.card, "cautious_start": {
        "steps": cfg.steps, "seconds": cfg.steps / student.config.control_hz, "friction_factor": cfg.friction_factor,
        "calibration_envs": cfg.calibration_envs, "calibration_seed": cfg.calibration_seed,
        "student": cfg.student, "teacher": cfg.teacher,
        "command": (f"python scripts/cautious_start.py --student {cfg.student} --teacher {cfg.teacher} --steps "
                    f"{cfg.steps} --friction-factor {cfg.friction_factor} --calibration-envs {cfg.calibration_envs} "
                    f"--calibration-seed {cfg.calibration_seed} --out {cfg.out}")}}
    config = replace(student.config, start_shift=tuple(float(v) for v in shift), start_steps=cfg.steps, card=card)
    PolicyBundle(config, student.net).save(cfg.out)
    print(f"cautious start: {cfg.steps} steps, latent shift {np.array2string(shift, precision=3)} -> {cfg.out}")
    return cfg.out


if __name__ == "__main__":
    raise SystemExit(script_main(Config, run, __doc__))
