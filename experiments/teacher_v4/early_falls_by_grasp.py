"""Are a slippery condition's early falls the grasps that cannot hold the cup? (the stage 11 record's third note)

    python experiments/teacher_v4/early_falls_by_grasp.py runs/eval_s11 friction_0.25

Reads a `rotate evaluate` run (its config's seed and episode count, each policy's per-episode ttf and time in hand
under CONDITION), finds the cached grasp each episode started from (a batch of envs reset as the evaluation resets
them: episode j seeded seed + j), runs the hold check on those grasps with the condition's friction factor on the
domes and the links (envs.grasps.HoldRule's ``surface``, the hand's nominal mass), and prints, per policy, the
falls within the first 2 s among the episodes whose grasp holds still by itself and among the others.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from envs.config import EnvConfig, default_randomization
from envs.core import RotateCupVec
from envs.grasp_cache import load_default_cache
from envs.grasps import HoldRule, hold_check
from rotation.evaluate.suites import get_suite

EARLY_S = 2.0


def evaluation_episodes(run: str, condition: str) -> tuple[RotateCupVec, dict[str, np.ndarray]]:
    """The episodes of a `rotate evaluate` run under CONDITION, reset as the evaluation reset them (a batch of envs,
    episode j seeded seed + j), and each policy's falls within the first EARLY_S seconds ((n,) bool)."""
    result = json.loads((Path(run) / "results.json").read_text())
    rows = [r for r in result["rows"] if r["condition"] == condition]
    if not rows:
        raise SystemExit(f"{Path(sys.argv[0]).stem}: no rows of {condition!r} in {run}")
    hand = "digit360_v4"
    perturb = next(c.perturb for c in get_suite("perturbations", (condition,), hand))
    n, seed = int(result["config"]["episodes"]), int(result["config"]["seed"])
    env = RotateCupVec(EnvConfig(hand=hand, randomization=default_randomization(hand), perturb=perturb),
                       num_envs=n, seed=seed, nthread=1)
    env.reset(seed=seed)
    early = {}
    for row in rows:
        per = row["per_episode"]
        early[row["policy"]] = (np.asarray(per["ttf"]) < 1.0) & (np.asarray(per["in_hand_time"]) <= EARLY_S)
    return env, early


def main(run: str, condition: str) -> int:
    env, early = evaluation_episodes(run, condition)
    n, hand, surface = env.num_envs, env.cfg.hand, env.cfg.perturb.friction_scale
    cache = load_default_cache("cup", "", hand)
    worst = hold_check(cache, HoldRule.for_hand(hand, surface=surface))
    holds = np.zeros(n, dtype=bool)
    for i, q in enumerate(env.grasp_q):
        s, g = np.argwhere(np.all(np.abs(cache.grasps[:, :, :16] - q) < 1e-5, axis=2))[0]
        holds[i] = worst[s, g] < HoldRule.max_tilt
    print(f"{condition}: {holds.sum()} of {n} episodes start from a grasp that holds the cup still by itself")
    for name, fell in early.items():
        print(f"  {name}: falls in the first {EARLY_S:g} s: {int((fell & holds).sum())} of "
              f"{int(holds.sum())} holding grasps, {int((fell & ~holds).sum())} of {int((~holds).sum())} others")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    raise SystemExit(main(sys.argv[1], sys.argv[2]))
