"""Does a slight opening of the fingers at the start keep slippery cups? (a diagnostic for issue 65's ceiling)

    python experiments/teacher_v4/start_opening.py --policy teacher --seed 11100000 --episodes 128 \\
        --conditions nominal friction_0.25 --offsets 0 -0.25 -0.5 -1 --steps 8

The policy acts as in `rotate evaluate` (deterministic, episode j seeded seed + j, the perturbation suite's
conditions on the vendor-kinematics hand), except that over its first ``--steps`` control steps each action gets
``offset`` added on the flexion joints (FLEXION: joints 1-3 of the index, middle and ring fingers, 2-3 of the
thumb; negative = open, one unit = ACTION_SCALE = 1/24 rad per step), clipped to [-1, 1] as the env clips it.
Every offset meets the same episodes, so the differences are paired. Prints, per condition and offset: ttf, the
falls within the first 2 s, the net rotation rate, and the paired difference in ttf to offset 0 with its standard
error; the last line is a JSON object with every figure.

The stage 11 record saw a scripted slight opening drop fewer slippery cups (13-15 of 64 against 19) with the
teacher of stage 10c; this measures it on the shipped teacher, and what it costs at nominal.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from envs.config import EnvConfig, default_randomization
from envs.core import RotateCupVec
from rotation.bundles import load_bundle
from rotation.evaluate.rollout import run_episodes
from rotation.evaluate.suites import get_suite

HAND = "digit360_v4"
FLEXION = np.array([1, 2, 3, 5, 6, 7, 9, 10, 11, 14, 15])
"""Joints whose positive action closes the finger (envs.constants: finger f owns joints 4f..4f+3, joint 0 of the
three fingers is abduction, joints 0-1 of the thumb turn it toward the palm)."""
EARLY_S = 2.0


class OpenAtStart:
    """A bundle that adds ``offset`` on FLEXION for the first ``steps`` actions after each env reset."""

    def __init__(self, bundle, env: RotateCupVec, offset: float, steps: int) -> None:
        self.bundle, self.offset, self.steps, self.k = bundle, offset, steps, 0
        self.config = bundle.config
        reset = env.reset

        def counted_reset(*args, **kwargs):
            self.k = 0
            return reset(*args, **kwargs)

        env.reset = counted_reset

    def start_correction(self, step: int) -> None:
        return None  # the start is this wrapper's own doing: no bundle shift on top

    def act_batch(self, groups: dict[str, np.ndarray]) -> np.ndarray:
        a = np.array(self.bundle.act_batch(groups), dtype=np.float32)
        if self.k < self.steps:
            a[:, FLEXION] = np.clip(a[:, FLEXION] + self.offset, -1.0, 1.0)
        self.k += 1
        return a


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", default="teacher")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--episodes", type=int, default=128)
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--conditions", nargs="+", default=["nominal", "friction_0.25"])
    p.add_argument("--offsets", nargs="+", type=float, default=[0.0, -0.25, -0.5, -1.0])
    p.add_argument("--steps", type=int, default=8)
    args = p.parse_args()
    if 0.0 not in args.offsets:
        p.error("--offsets must include 0 (the policy as it is: the paired baseline)")
    bundle = load_bundle(args.policy)
    out: dict = {"seed": args.seed, "episodes": args.episodes, "steps": args.steps, "conditions": {}}
    for cond in get_suite("perturbations", tuple(args.conditions), HAND):
        env = RotateCupVec(EnvConfig(hand=HAND, randomization=default_randomization(HAND), perturb=cond.perturb),
                           num_envs=args.num_envs, seed=args.seed, nthread=1)
        ttf, rows = {}, {}
        for offset in [0.0] + [o for o in args.offsets if o != 0.0]:  # the baseline first: the others pair with it
            eps = run_episodes(OpenAtStart(bundle, env, offset, args.steps), env, args.episodes, args.seed)
            ttf[offset] = np.array([e.ttf for e in eps])
            early = sum(e.fell and e.in_hand_time <= EARLY_S for e in eps)
            rate = sum(e.rotation_total for e in eps) / max(sum(e.in_hand_time for e in eps), 1e-9)
            d = ttf[offset] - ttf[0.0]
            se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else 0.0
            rows[offset] = {"ttf": float(ttf[offset].mean()), "early_falls": int(early),
                            "falls": int(sum(e.fell for e in eps)), "net_rate": float(rate),
                            "ttf_vs_0": float(d.mean()), "se": se}
            r = rows[offset]
            print(f"{cond.name:<26} offset {offset:+.2f} x {args.steps} steps: ttf {r['ttf']:.3f}, falls "
                  f"{r['falls']} ({r['early_falls']} in {EARLY_S:g} s), net {r['net_rate']:.3f} rad/s, "
                  f"ttf - offset 0: {r['ttf_vs_0']:+.3f} +- {r['se']:.3f}", flush=True)
        env.close()
        out["conditions"][cond.name] = {str(k): v for k, v in rows.items()}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
