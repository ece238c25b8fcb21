"""How much each dimension of the teacher's latent z moves under the low-friction and added-mass perturbations.

The teacher's env-factor encoder maps the privileged vector (object position, scale, mass, friction, center of mass)
to z. This script draws episodes' privileged vectors from the env's randomization (resets only, no rollout), applies
each perturbation to them (friction x factor, mass + kg, as ``rotate evaluate``'s conditions do) and prints, per
dimension of z, the mean absolute change. It also gives the share of each dimension that the mass perturbation
explains, ``|dz_mass| / (|dz_mass| + |dz_friction|)``: per-dimension weights for an adapter ensemble whose members
are better at one perturbation each (``rotate ensemble-adapters --dim-weights``)::

    python experiments/tools/latent_sensitivity.py --episodes 512 --seed 0

Its last line is a JSON object (``mass_share`` and the two changes, one number per dimension).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from envs.constants import PRIV_FIELDS
from envs.rotate_cup import RotateCupEnv
from rotation.bundles import load_bundle
from rotation.configs import script_main


@dataclass
class Config:
    teacher: str = "teacher"
    """Teacher bundle (a shipped name or a directory) whose env-factor encoder gives z."""
    episodes: int = 512
    """Privileged vectors to draw (one env reset each)."""
    seed: int = 0
    """Seed of the first reset (the others follow it)."""
    friction_scale: float = 0.25
    """The low-friction perturbation: friction x this."""
    added_mass: float = 0.2
    """The added-mass perturbation (kg)."""

    def __post_init__(self) -> None:
        if not 1 <= self.episodes <= 100_000:
            raise ValueError(f"--episodes must be in [1, 100000], got {self.episodes}")
        if not 0 < self.friction_scale <= 1:
            raise ValueError(f"--friction-scale must be in (0, 1], got {self.friction_scale}")
        if not 0 < self.added_mass <= 0.5:
            raise ValueError(f"--added-mass must be in (0, 0.5] kg, got {self.added_mass}")


def run(cfg: Config) -> dict[str, list[float]]:
    teacher = load_bundle(cfg.teacher).require("privileged", f"--teacher {cfg.teacher!r}")
    encoder = teacher.net.extractor.encoder
    env = RotateCupEnv()
    try:
        priv = np.array([env.reset(seed=cfg.seed + i)[0]["priv"]
                         for i in tqdm(range(cfg.episodes), desc="privileged vectors", unit="reset")])
    finally:
        env.close()
    p = torch.as_tensor(priv, dtype=torch.float32)
    slippery, heavy = p.clone(), p.clone()
    slippery[:, PRIV_FIELDS.index("friction")] *= cfg.friction_scale
    heavy[:, PRIV_FIELDS.index("mass")] += cfg.added_mass
    with torch.no_grad():
        z = encoder(p)
        d_friction = (encoder(slippery) - z).abs().mean(0)
        d_mass = (encoder(heavy) - z).abs().mean(0)
    share = d_mass / (d_mass + d_friction).clamp_min(1e-12)
    out = {"friction_change": d_friction.tolist(), "mass_change": d_mass.tolist(), "mass_share": share.tolist()}
    print(f"{'dim':>3} {'|dz| friction x' + format(cfg.friction_scale, 'g'):>20} "
          f"{'|dz| mass +' + format(cfg.added_mass, 'g') + ' kg':>18} {'mass share':>10}")
    for d in range(len(share)):
        print(f"{d:>3} {d_friction[d]:>20.3f} {d_mass[d]:>18.3f} {share[d]:>10.3f}")
    print(json.dumps({k: [round(v, 4) for v in vals] for k, vals in out.items()}))
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
