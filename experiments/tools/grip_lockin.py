"""How much of a shaken bottle's contents the fingertips feel, per grip: a lock-in at the shaking frequency.

    python experiments/tools/grip_lockin.py fingertips 10 90
    python experiments/tools/grip_lockin.py palm 10 90

For each seed (envs.shake.draw_episode, content and fill drawn), the episode is shaken with the bottle held by
``grip`` (envs.shake.ShakeConfig.grip); after the settling and the ramp, each fingertip's normal and two shear forces
(the contact fields the Digit 360 streams are rendered from) are demodulated at the wrist's frequency and phase.
The norm of the 12 amplitudes over the wrist's acceleration amplitude is the mass the domes feel move with the hand
(kg). A bottle "held" moved at most HELD_TOLERANCE (15 mm) in the palm's frame after the settling (the session's
own ``held`` counts the settling too). Prints a row per episode and, over the held ones, the correlation of that
mass with the contents' mass, and the domes' mean summed normal force.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from envs.grasp_cache import load_default_cache
from envs.sensors.digit360 import FIELD
from envs.shake import HELD_TOLERANCE, TIMESTEP, ShakeConfig, ShakeSim, draw_episode

CHANNELS = ("force_n", "force_x", "force_y")


def felt_mass(cfg: ShakeConfig, seed: int, grasps) -> tuple:
    ep = draw_episode(cfg, seed, grasps)
    rec = ShakeSim(cfg, ep, grasps).run()
    t = rec.times
    keep = t > cfg.settle_s + cfg.ramp_s
    w = 2 * math.pi * ep.frequency
    amplitudes = []
    for finger in range(4):
        d = rec.contact[finger][keep]
        for name in CHANNELS:
            x = d[:, FIELD[name]] - d[:, FIELD[name]].mean()
            amplitudes.append(2 * np.mean(x * np.exp(-1j * (w * t[keep] + ep.phase))))
    felt = float(np.linalg.norm(np.abs(amplitudes)) / (ep.amplitude * w * w))
    settled = int(cfg.settle_s / TIMESTEP)
    held = bool(np.linalg.norm(rec.bottle_offset[-1] - rec.bottle_offset[settled]) <= HELD_TOLERANCE)
    normal = float(sum(rec.contact[f][keep][:, FIELD["force_n"]].mean() for f in range(4)))
    return ep, rec.content_mass, felt, held, normal


def main(grip: str, first: int, last: int) -> None:
    cfg = ShakeConfig(grip=grip)
    grasps = load_default_cache("cup", "", cfg.hand)
    rows, t0 = [], time.time()
    for seed in range(first, last):
        ep, mass, felt, held, normal = felt_mass(cfg, seed, grasps)
        rows.append((mass, felt, held, normal))
        print(f"{grip} seed={seed} {ep.content:8s} fill={ep.fill} m={mass * 1e3:5.0f}g felt={felt:.3f}kg held={held} "
              f"normal={normal:.2f}N", flush=True)
    r = np.array(rows, float)
    h = r[:, 2] > 0
    print(f"{grip}: held {int(h.sum())}/{len(r)}; correlation of the felt mass with the contents' mass (held): "
          f"{np.corrcoef(r[h, 0], r[h, 1])[0, 1]:.2f}; domes' mean normal force {r[h, 3].mean():.2f} N; "
          f"{time.time() - t0:.0f} s")


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]))
