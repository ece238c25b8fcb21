"""How much the joints' tracking says about the cup's mass, next to what the student's phi(history) says.

The palm and the phalanges carry the cup on the palm-up hand (experiments/tools/load_share.py), and their joints are
position-controlled: a heavier cup makes them sag. This script rolls the student out at nominal and with added mass
(the same episodes, the env's training randomization) and, at every ``every``-th control step after ``warmup`` of
every episode that has not ended, records:

- the student's latent phi(history) (8 numbers);
- the joints' tracking over the same 30-step history (48 numbers: per joint the mean and the spread of target -
  position, and the mean position; adapters.model.tracking_features, what ``finetune-adapter --tracking`` feeds an
  adapter);
- the cup's true mass and the teacher's latent z.

It fits ridge regressions from each feature set to the mass and to each of the teacher's latent dimensions named by
``--dims`` on the even-numbered episodes and reports R² on the odd ones (the episodes an estimate never saw), and
how far apart the held-out nominal and heavy episodes' mean predictions lie, in standard deviations of the nominal
episodes.

    python experiments/tools/mass_from_joints.py --envs 64 --steps 200 --seed 2100800

The last line printed is a JSON object with every figure.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from adapters.model import tracking_features
from envs.config import Perturbation
from envs.constants import PRIV_FIELDS
from envs.core import RotateCupVec
from envs.rotate_cup import config_from_kwargs
from rotation.bundles import load_bundle, policy_hand
from rotation.configs import script_main

FEATURES = ("phi", "tracking", "phi+tracking")
"""The feature sets compared: the student's latent, the joints' tracking, both."""


@dataclass
class Config:
    student: str = "student"
    """The student bundle that acts and whose phi is read (a shipped name or a directory)."""
    teacher: str = "teacher"
    """The teacher bundle whose latent z is a target."""
    envs: int = 64
    """Episodes per condition, run side by side."""
    steps: int = 200
    """Control steps per episode (10 s at 20 Hz)."""
    warmup: int = 40
    """Control steps before the first sample (the history fills, the grasp settles)."""
    every: int = 5
    """Control steps between two samples of an episode."""
    seed: int = 2100800
    """Seed of the episodes; both conditions run the same ones."""
    added_mass: float = 0.2
    """The added-mass condition (kg)."""
    dims: tuple[int, ...] = (2,)
    """Teacher latent dimensions to predict besides the mass (2: the one +0.2 kg moves most)."""
    ridge: float = 0.01
    """Ridge strength (times the number of training samples) on standardized features."""

    def __post_init__(self) -> None:
        if not 2 <= self.envs <= 1024:
            raise ValueError(f"--envs must be in [2, 1024] (even episodes fit, odd ones test), got {self.envs}")
        if not 0 <= self.warmup < self.steps:
            raise ValueError(f"--warmup must be in [0, --steps), got warmup {self.warmup}, steps {self.steps}")
        if self.every < 1:
            raise ValueError(f"--every must be at least 1, got {self.every}")
        if not 0 < self.added_mass <= 0.25:
            raise ValueError(f"--added-mass must be in (0, 0.25] kg, got {self.added_mass}")
        if self.ridge <= 0:
            raise ValueError(f"--ridge must be positive, got {self.ridge}")


def ridge_fit_predict(x: np.ndarray, y: np.ndarray, train: np.ndarray, strength: float) -> np.ndarray:
    """Predictions for every row of ``x`` (n, d) of a ridge regression of ``y`` (n,) fitted on the rows ``train``
    (boolean), the features standardized by the training rows and an unpenalized intercept."""
    mu, sd = x[train].mean(0), x[train].std(0) + 1e-8
    xs = np.c_[(x - mu) / sd, np.ones(len(x))]
    a = xs[train]
    penalty = strength * len(a) * np.eye(a.shape[1])
    penalty[-1, -1] = 0.0
    w = np.linalg.solve(a.T @ a + penalty, a.T @ (y[train] - y[train].mean()))
    return xs @ w + y[train].mean()


def r2(pred: np.ndarray, y: np.ndarray) -> float:
    """Coefficient of determination of ``pred`` against ``y`` (1 = exact, 0 = no better than the mean)."""
    return float(1.0 - ((pred - y) ** 2).mean() / max(float(y.var()), 1e-12))


def separation(pred: np.ndarray, episode: np.ndarray, heavy: np.ndarray) -> float:
    """Heavy minus nominal episodes' mean prediction, in standard deviations of the nominal episodes' means."""
    means = {h: np.array([pred[(episode == e) & (heavy == h)].mean() for e in np.unique(episode[heavy == h])])
             for h in (False, True)}
    sd = float(np.std(means[False], ddof=1)) if len(means[False]) > 1 else float("nan")
    return float((means[True].mean() - means[False].mean()) / max(sd, 1e-12))


def collect(cfg: Config) -> dict[str, np.ndarray]:
    """Roll the student out at nominal and with added mass; every sample's features, targets and episode."""
    student, teacher = load_bundle(cfg.student), load_bundle(cfg.teacher)
    student.require("adaptation", f"--student {cfg.student}")
    teacher.require("privileged", f"--teacher {cfg.teacher}")
    if any(not 0 <= d < teacher.config.latent_dim for d in cfg.dims):
        raise ValueError(f"--dims must name latent dimensions 0..{teacher.config.latent_dim - 1}, got {list(cfg.dims)}")
    rows: dict[str, list] = {k: [] for k in ("phi", "tracking", "mass", "z", "episode", "heavy")}
    for heavy, perturb in ((False, Perturbation()), (True, Perturbation(added_mass=cfg.added_mass))):
        env = RotateCupVec(config_from_kwargs(perturb=perturb, hand=policy_hand(student)), num_envs=cfg.envs,
                           seed=cfg.seed)  # the student's own hand (and that hand's physics)
        try:
            obs = env.reset(seed=cfg.seed)
            alive = np.ones(cfg.envs, bool)
            desc = f"+{cfg.added_mass:g} kg" if heavy else "nominal"
            for t in tqdm(range(cfg.steps), desc=desc, unit="step", leave=False):
                obs, _, terminated, truncated, _ = env.step(student.act_batch(obs))
                alive &= ~(terminated | truncated)
                if t < cfg.warmup or (t - cfg.warmup) % cfg.every or not alive.any():
                    continue
                idx = np.flatnonzero(alive)
                rows["phi"].append(student.latent(obs)[idx])
                rows["tracking"].append(tracking_features(torch.as_tensor(obs["proprio_hist"][idx])).numpy())
                rows["mass"].append(obs["priv"][idx, PRIV_FIELDS.index("mass")])
                rows["z"].append(teacher.latent(obs)[idx])
                rows["episode"].append(idx)
                rows["heavy"].append(np.full(len(idx), heavy))
        finally:
            env.close()
    if not rows["phi"]:
        raise ValueError("every episode ended within the warm-up: nothing to fit (lower --warmup)")
    return {k: np.concatenate(v).astype(np.float64 if k not in ("episode", "heavy") else v[0].dtype)
            for k, v in rows.items()}


def run(cfg: Config) -> dict[str, dict[str, dict[str, float]]]:
    data = collect(cfg)
    z = data["z"]
    features = {"phi": data["phi"], "tracking": data["tracking"],
                "phi+tracking": np.c_[data["phi"], data["tracking"]]}
    targets = {"mass": data["mass"], **{f"teacher z[{d}]": z[:, d] for d in cfg.dims}}
    train = data["episode"] % 2 == 0
    test = ~train
    result: dict[str, dict[str, dict[str, float]]] = {}
    for tname, y in targets.items():
        result[tname] = {}
        for fname in FEATURES:
            pred = ridge_fit_predict(features[fname], y, train, cfg.ridge)
            result[tname][fname] = {
                "r2": round(r2(pred[test], y[test]), 3),
                "separation": round(separation(pred[test], data["episode"][test], data["heavy"][test]), 2)}
    n_test = len(np.unique(data["episode"][test]))
    samples = len(data["mass"])
    print(f"{cfg.student}: {samples} samples of {cfg.envs} episodes per condition (nominal, "
          f"+{cfg.added_mass:g} kg), fitted on the even episodes, R² on the {n_test} odd ones per condition; "
          "separation: heavy minus nominal episodes' mean prediction in nominal standard deviations")
    print(f"{'target':<14}" + "".join(f"{f + ' R²':>20}{'sep':>7}" for f in FEATURES))
    for tname, row in result.items():
        print(f"{tname:<14}" + "".join(f"{row[f]['r2']:>20.3f}{row[f]['separation']:>+7.2f}" for f in FEATURES))
    print(json.dumps({"student": cfg.student, "teacher": cfg.teacher, "envs": cfg.envs, "steps": cfg.steps,
                      "seed": cfg.seed, "samples": samples, "result": result}))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
