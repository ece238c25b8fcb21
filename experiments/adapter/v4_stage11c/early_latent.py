"""How much of the student's gap is what the teacher knows in the first seconds? (a diagnostic, no decision)

    cd experiments/adapter/v4_stage11c
    python early_latent.py --seed 11300000 --episodes 128 --steps 20 40

Policies, each on the same episodes (deterministic, episode j seeded seed + j, the perturbation suite's conditions
on the vendor-kinematics hand), for each K in ``--steps`` (control steps at 20 Hz):

- ``student``, ``teacher``: as shipped;
- ``oracle_first_K``: the student's actor on the teacher's true z (the oracle-latent student) for the first K steps,
  then the student as it is: the gain of knowing the cup only at the start;
- ``teacher_believes_x4_first_K`` (slippery conditions): the teacher whose privileged friction reads 4 times the true
  one for its first K steps (a slippery cup taken for a nominal one), then the truth: what not knowing costs early;
- ``teacher_believes_x0.25_first_K`` (nominal): the teacher taking a nominal cup for one at a quarter of its friction
  for its first K steps: what a cautious start costs where caution was not needed;
- with ``--cautious``, instead of the last three, ``student_cautious_first_K``: the student whose latent gets, for its
  first K steps, a fixed shift toward slippery cups: the mean over ``--calibration-envs`` starts of the training
  randomization (seeded ``--calibration-seed``, disjoint from the evaluation's) of the teacher's z with the friction
  at a quarter minus its z with the true friction. A constant vector, so a real hand could use it too.

Prints, per condition and policy: ttf, falls (within the first 2 s), the net rotation rate, and the paired
difference in ttf to the student; the last line is a JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
from types import SimpleNamespace

import numpy as np
import torch

from envs.config import EnvConfig, default_randomization
from envs.constants import PRIV_FIELDS
from envs.core import RotateCupVec
from rotation.bundles import load_bundle
from rotation.evaluate.rollout import run_episodes
from rotation.evaluate.suites import get_suite

HAND = "digit360_v4"
EARLY_S = 2.0
FRICTION = PRIV_FIELDS.index("friction")


class StepCounter:
    """Counts the actions since the env's last reset (``k``): every env of a chunk starts together in
    rotation.evaluate.rollout.run_episodes, so one count serves the whole batch."""

    def __init__(self, env: RotateCupVec) -> None:
        self.k = 0
        reset = env.reset

        def counted_reset(*args, **kwargs):
            self.k = 0
            return reset(*args, **kwargs)

        env.reset = counted_reset

    def start_correction(self, step: int) -> None:
        return None  # the start is this wrapper's own doing: no bundle shift on top


class FirstSteps(StepCounter):
    """Acts with ``first`` for the first ``steps`` actions after each env reset, then with ``then``; ``first_priv``
    scales the privileged friction that ``first`` sees (1: the truth)."""

    def __init__(self, env: RotateCupVec, first, then, steps: int, first_priv: float = 1.0) -> None:
        super().__init__(env)
        self.first, self.then, self.steps, self.scale = first, then, steps, first_priv
        self.config = SimpleNamespace(obs_groups={**then.config.obs_groups, **first.config.obs_groups})

    def act_batch(self, groups: dict[str, np.ndarray]) -> np.ndarray:
        use = self.first if self.k < self.steps else self.then
        self.k += 1
        mine = {key: groups[key] for key in use.config.obs_groups}
        if use is self.first and self.scale != 1.0:
            mine["priv"] = mine["priv"].copy()
            mine["priv"][:, FRICTION] *= self.scale
        return use.act_batch(mine)


class CautiousStart(StepCounter):
    """The student acting on its latent plus ``shift`` for the first ``steps`` actions after each env reset."""

    def __init__(self, env: RotateCupVec, student, shift: np.ndarray, steps: int) -> None:
        super().__init__(env)
        self.student, self.shift, self.steps = student, torch.as_tensor(shift), steps
        self.config = student.config

    @torch.no_grad()
    def act_batch(self, groups: dict[str, np.ndarray]) -> np.ndarray:
        self.k += 1
        if self.k > self.steps:
            return self.student.act_batch(groups)
        tensors = self.student._tensors(groups, batched=True)
        z = self.student.net.extractor.z(tensors) + self.shift
        return self.student.net.mean(tensors, z).clamp(-1.0, 1.0).numpy()


def slippery_shift(teacher, n: int, seed: int) -> np.ndarray:
    """Mean over n starts of the training randomization of the teacher's z at a quarter of the friction minus its z."""
    env = RotateCupVec(EnvConfig(hand=HAND, randomization=default_randomization(HAND)), num_envs=n, seed=seed,
                       nthread=1)
    obs = env.reset(seed=seed)
    env.close()
    groups = {key: obs[key] for key in teacher.config.obs_groups}
    slippery = {**groups, "priv": groups["priv"].copy()}
    slippery["priv"][:, FRICTION] *= 0.25
    return (teacher.latent(slippery) - teacher.latent(groups)).mean(axis=0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--episodes", type=int, default=128)
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--conditions", nargs="+", default=["nominal", "friction_0.25"])
    p.add_argument("--steps", nargs="+", type=int, default=[20, 40])
    p.add_argument("--cautious", action="store_true")
    p.add_argument("--calibration-envs", type=int, default=256)
    p.add_argument("--calibration-seed", type=int, default=0)
    args = p.parse_args()
    teacher, student = load_bundle("teacher"), load_bundle("student")
    oracle = student.with_teacher_latent(teacher)
    out: dict = {"seed": args.seed, "episodes": args.episodes, "conditions": {}}
    if args.cautious:
        if not args.calibration_seed:
            p.error("--cautious needs --calibration-seed (seeds no evaluation episode uses)")
        shift = slippery_shift(teacher, args.calibration_envs, args.calibration_seed)
        out["shift"] = shift.tolist()
        print(f"slippery shift of the latent ({args.calibration_envs} starts, seed {args.calibration_seed}): "
              f"{np.array2string(shift, precision=3)}", flush=True)
    for cond in get_suite("perturbations", tuple(args.conditions), HAND):
        env = RotateCupVec(EnvConfig(hand=HAND, randomization=default_randomization(HAND), perturb=cond.perturb),
                           num_envs=args.num_envs, seed=args.seed, nthread=1)
        slippery = cond.perturb.friction_scale < 1.0
        policies = {"student": FirstSteps(env, student, student, 0), "teacher": FirstSteps(env, teacher, teacher, 0)}
        for k in args.steps:
            if args.cautious:
                policies[f"student_cautious_first_{k}"] = CautiousStart(env, student, shift, k)
                continue
            policies[f"oracle_first_{k}"] = FirstSteps(env, oracle, student, k)
            name, scale = ("teacher_believes_x4", 4.0) if slippery else ("teacher_believes_x0.25", 0.25)
            policies[f"{name}_first_{k}"] = FirstSteps(env, teacher, teacher, k, first_priv=scale)
        ttf, rows = {}, {}
        for name, policy in policies.items():
            eps = run_episodes(policy, env, args.episodes, args.seed)
            ttf[name] = np.array([e.ttf for e in eps])
            d = ttf[name] - ttf["student"]
            rate = sum(e.rotation_total for e in eps) / max(sum(e.in_hand_time for e in eps), 1e-9)
            rows[name] = {"ttf": float(ttf[name].mean()), "falls": int(sum(e.fell for e in eps)), "net_rate": rate,
                          "early_falls": int(sum(e.fell and e.in_hand_time <= EARLY_S for e in eps)),
                          "ttf_vs_student": float(d.mean()), "se": float(d.std(ddof=1) / np.sqrt(len(d)))}
            r = rows[name]
            print(f"{cond.name:<16} {name:<30} ttf {r['ttf']:.3f}, falls {r['falls']} ({r['early_falls']} in "
                  f"{EARLY_S:g} s), net {r['net_rate']:.3f} rad/s, - student {r['ttf_vs_student']:+.3f} "
                  f"+- {r['se']:.3f}", flush=True)
        env.close()
        out["conditions"][cond.name] = rows
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
