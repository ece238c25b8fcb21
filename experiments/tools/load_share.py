"""Who carries the cup: the contact forces on the object from the Digit 360 fingertip domes and from the rest of the
hand.

A Digit 360 senses only what touches its dome. This script measures how much of the object's weight reaches the
domes at all. For each condition (nominal, low friction, added mass), it rolls a policy out in the batched env
(the training randomization, as ``rotate evaluate`` uses by default). At every control step after a warm-up, for
every episode that has not ended, it sums the contact forces on the object by what exerts them:

- the four fingertip domes (``<finger>_tip``);
- the rest of the hand (the palm and the phalanges, which no Digit 360 covers);
- the floor.

Per condition it prints the object's weight m g and the world-vertical force from the domes and from the rest of
the hand, in newtons and as shares of m g; each is a mean over the counted steps, so an episode that ends early
counts less. The remainder is the object's acceleration and the random pushes. It also prints the mean normal and
tangential contact force summed over the four domes (what their elastomers feel), and how far the condition moves
each episode's ratio of the two: the difference from nominal in standard deviations of the nominal episodes.

    python experiments/tools/load_share.py --policy student --envs 16 --steps 160 --seed 2100700

On the palm-up hand, the palm and the phalanges carry the cup and the domes only push it around. So an added mass
reaches the fingertips only as the shear of pushing a heavier cup (docs/adapter.md).
The last line printed is a JSON object with every figure.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import mujoco
import numpy as np
from tqdm import tqdm

from envs.config import Perturbation
from envs.constants import FINGERS
from envs.core import RotateCupVec
from envs.rotate_cup import config_from_kwargs
from rotation.bundles import load_bundle, policy_hand
from rotation.configs import script_main
from rotation.evaluate.suites import condition_name

SOURCES = ("domes", "hand", "floor")
"""What exerts a contact force on the object: the fingertip domes, the rest of the hand, the floor."""
COLUMNS = (*(f"{s}_z" for s in SOURCES), "weight", "dome_normal", "dome_tangential")
"""What is averaged over the counted steps: the vertical force from each source, m g, and the dome forces (N)."""


@dataclass
class Config:
    policy: str = "student"
    """Policy bundle to roll out (a shipped name or a directory)."""
    envs: int = 16
    """Episodes per condition, run side by side (env slot i is seeded seed + i)."""
    steps: int = 160
    """Control steps per episode (8 s at 20 Hz); an episode that ends earlier stops counting."""
    warmup: int = 20
    """Control steps before the forces are counted (the grasp settles)."""
    seed: int = 2100700
    """Seed of the episodes; every condition runs the same ones."""
    friction_scale: float = 0.25
    """The low-friction condition: friction x this."""
    added_mass: float = 0.2
    """The added-mass condition (kg)."""

    def __post_init__(self) -> None:
        if not 1 <= self.envs <= 1024:
            raise ValueError(f"--envs must be in [1, 1024], got {self.envs}")
        if not 0 <= self.warmup < self.steps:
            raise ValueError(f"--warmup must be in [0, --steps), got warmup {self.warmup}, steps {self.steps}")
        if not 0 < self.friction_scale <= 1:
            raise ValueError(f"--friction-scale must be in (0, 1], got {self.friction_scale}")
        if not 0 < self.added_mass <= 0.25:
            raise ValueError(f"--added-mass must be in (0, 0.25] kg, got {self.added_mass}")


def object_forces(model: mujoco.MjModel, data: mujoco.MjData, obj: int, domes: set[int], floor: int
                  ) -> dict[str, np.ndarray]:
    """World-frame contact forces (N) on body ``obj`` by source: ``domes`` (the fingertip geoms), ``floor`` (that
    geom), ``hand`` (any other geom); plus ``dome_normal`` and ``dome_tangential``, the magnitudes of the normal and
    tangential parts summed over the dome contacts."""
    out = {s: np.zeros(3) for s in SOURCES}
    normal = tangential = 0.0
    f6 = np.zeros(6)
    for i in range(data.ncon):
        con = data.contact[i]
        b1, b2 = model.geom_bodyid[con.geom1], model.geom_bodyid[con.geom2]
        if obj not in (b1, b2) or b1 == b2:
            continue
        mujoco.mj_contactForce(model, data, i, f6)  # contact frame: normal, then the two tangential directions
        world = con.frame.reshape(3, 3).T @ f6[:3]  # what geom1 exerts on geom2
        other = con.geom1 if b2 == obj else con.geom2
        force = world if b2 == obj else -world
        source = "domes" if other in domes else "floor" if other == floor else "hand"
        out[source] += force
        if source == "domes":
            normal += abs(f6[0])
            tangential += float(np.hypot(f6[1], f6[2]))
    return {**out, "dome_normal": np.array(normal), "dome_tangential": np.array(tangential)}


def measure(cfg: Config, bundle, perturb: Perturbation) -> dict[str, float]:
    """One condition's mean forces over the counted steps of every episode."""
    env = RotateCupVec(config_from_kwargs(perturb=perturb, hand=policy_hand(bundle)), num_envs=cfg.envs,
                       seed=cfg.seed)  # the policy's own hand (and that hand's physics)
    try:
        model, _ = env.get_data(0)
        obj = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")
        domes = {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"{f}_tip") for f in FINGERS}
        floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
        if obj < 0 or -1 in domes or floor < 0:
            raise ValueError("the env's model lacks the body 'object', a '<finger>_tip' geom or the geom 'floor'")
        obs = env.reset(seed=cfg.seed)
        weight = np.array([m.body_subtreemass[obj] * float(np.linalg.norm(m.opt.gravity))
                           for m in (env.get_data(i)[0] for i in range(cfg.envs))])
        alive = np.ones(cfg.envs, bool)
        samples = 0  # counted steps, over every episode
        totals = np.zeros((cfg.envs, len(COLUMNS)))  # each episode's sums over its counted steps
        for step in tqdm(range(cfg.steps), desc=condition_name(perturb), unit="step", leave=False):
            obs, _, terminated, truncated, _ = env.step(bundle.act_batch(obs))
            alive &= ~(terminated | truncated)
            if step < cfg.warmup:
                continue
            for i in np.flatnonzero(alive):
                m, d = env.get_data(i)
                f = object_forces(m, d, obj, domes, floor)
                totals[i] += (*(f[s][2] for s in SOURCES), weight[i], f["dome_normal"], f["dome_tangential"])
                samples += 1
    finally:
        env.close()
    out = {"samples": samples, "episodes_to_the_end": int(alive.sum())}
    if samples:
        mean = dict(zip(COLUMNS, totals.sum(0) / samples, strict=True))
        out.update({k: round(float(v), 4) for k, v in mean.items()})
        for s in ("domes", "hand"):
            out[f"{s}_share"] = round(float(mean[f"{s}_z"] / mean["weight"]), 4)
    normal, tangential = totals[:, COLUMNS.index("dome_normal")], totals[:, COLUMNS.index("dome_tangential")]
    touched = normal > 0
    out["episode_ratio"] = [round(float(r), 4) for r in tangential[touched] / normal[touched]]
    return out


def separation(ratios: list[float], nominal: list[float]) -> float | None:
    """How far a condition moves the per-episode tangential/normal dome force ratio: the difference of the means in
    standard deviations of the nominal episodes (None with fewer than two nominal episodes or none here)."""
    if len(nominal) < 2 or not ratios:
        return None
    sd = float(np.std(nominal, ddof=1))
    return round((float(np.mean(ratios)) - float(np.mean(nominal))) / max(sd, 1e-12), 2)


def run(cfg: Config) -> dict[str, dict[str, float]]:
    bundle = load_bundle(cfg.policy)
    if getattr(bundle, "touch_every", 0):
        raise ValueError(f"--policy {cfg.policy}: a tactile adapter; this script runs without touch, where it would "
                         "act as its student alone: give the student")
    conditions = (Perturbation(), Perturbation(friction_scale=cfg.friction_scale),
                  Perturbation(added_mass=cfg.added_mass))
    result = {condition_name(p): measure(cfg, bundle, p) for p in conditions}
    nominal = result[condition_name(conditions[0])]["episode_ratio"]
    for r in result.values():
        r["ratio_separation"] = separation(r["episode_ratio"], nominal)
    print(f"{cfg.policy}, {cfg.envs} episodes, steps {cfg.warmup}-{cfg.steps} (forces on the object, N; separation: "
          "the episodes' dome tangential/normal ratio against nominal, in nominal standard deviations):")
    print(f"{'condition':<15} {'m g':>6} {'domes up':>15} {'rest of hand up':>16} {'dome normal':>12} "
          f"{'dome tangential':>16} {'separation':>11}")
    for name, r in result.items():
        if not r["samples"]:
            print(f"{name:<15} every episode ended within the warm-up: nothing measured")
            continue
        sep = "-" if r["ratio_separation"] is None else f"{r['ratio_separation']:+.2f}"
        print(f"{name:<15} {r['weight']:>6.2f} {r['domes_z']:>7.2f} ({r['domes_share']:>4.0%}) "
              f"{r['hand_z']:>8.2f} ({r['hand_share']:>4.0%}) {r['dome_normal']:>12.2f} {r['dome_tangential']:>16.2f} "
              f"{sep:>11}")
    print(json.dumps({"policy": cfg.policy, "envs": cfg.envs, "steps": cfg.steps, "seed": cfg.seed, **result}))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
