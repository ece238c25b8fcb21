"""Which episodes' draws fall early? (the stage 11d record's diagnostic)

    python experiments/teacher_v4/early_falls_by_draw.py runs/eval_s11d friction_0.25

Reads a `rotate evaluate` run (its seed and episode count, each policy's per-episode ttf and time in hand under
CONDITION), resets a batch of envs as the evaluation resets them (episode j seeded seed + j) to recover every
episode's draws (gel friction after the condition's factor, mass, cup scale, action delay, contact time constant,
the noslip solver on or off), and prints, per policy and draw, the share of episodes that fall within the first 2 s
in each third of the draw (on or off for the solver), and how many early falls the policies share.
"""

from __future__ import annotations

import sys

import numpy as np
from early_falls_by_grasp import EARLY_S, evaluation_episodes  # (this folder: run as a script)

DRAWS = ("friction", "mass", "scale", "delay", "timeconst")


def main(run: str, condition: str) -> int:
    env, early = evaluation_episodes(run, condition)
    n = env.num_envs
    params = {k: np.asarray(env.params[k], dtype=float).reshape(n) for k in (*DRAWS, "noslip")}
    for name, fell in early.items():
        print(f"{condition}, {name}: {int(fell.sum())} of {n} fall within {EARLY_S:g} s")
        for k in DRAWS:
            edges = np.quantile(params[k], [0, 1 / 3, 2 / 3, 1])
            thirds = np.clip(np.searchsorted(edges, params[k], side="right") - 1, 0, 2)
            shares = ", ".join(f"{edges[i]:.3g}-{edges[i + 1]:.3g}: {fell[thirds == i].mean():.2f}" for i in range(3))
            print(f"  {k:<10} by thirds {shares}")
        on = params["noslip"] > 0
        print(f"  noslip     off: {fell[~on].mean():.2f} of {int((~on).sum())}, on: {fell[on].mean():.2f} of "
              f"{int(on.sum())}")
    names = list(early)
    if len(names) == 2:
        a, b = early[names[0]], early[names[1]]
        print(f"early falls of both {names[0]} and {names[1]}: {int((a & b).sum())}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    raise SystemExit(main(sys.argv[1], sys.argv[2]))
