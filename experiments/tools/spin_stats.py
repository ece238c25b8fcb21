"""Per-step spin of policies about the commanded axis: does a policy turn the cup, or ratchet it back and forth?

The rotate reward term is clip(spin, -rotate_back_clip, rotate_clip) per policy step. With Hora's symmetric 0.5 a
policy can earn it without turning the cup: forward at the cap, then a snap back faster than the cap, which costs
only the cap. This script rolls each policy out (deterministic actions, nominal randomization, episode j seeded
``seed + j`` as in `rotate evaluate`) and compares, over the in-hand steps, the mean spin (what the cup really
does) with the mean clipped spin at the given clips (what the reward pays), the fraction of steps past each cap, and
a histogram of the spin per policy (``spin.png``).

    python experiments/tools/spin_stats.py --policies teacher student scratch=runs/scratch_nolap/bundle --out runs/spin

The last line printed is a JSON object with every figure.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from rotation.configs import script_main  # noqa: E402


@dataclass
class Config:
    """Spin statistics settings."""

    policies: tuple[str, ...] = ("teacher",)
    """Policy bundles: shipped names, directories, or NAME=PATH."""
    episodes: int = 32
    """Episodes per policy (run side by side, one env each)."""
    episode_steps: int = 400
    """Policy steps per episode (20 s at 20 Hz)."""
    seed: int = 910000
    """Episode j is seeded seed + j."""
    rotate_clip: float = 0.5
    """Upper clip of the reward term the clipped mean uses (rad/s)."""
    rotate_back_clip: float = 0.5
    """Lower clip, as a positive number (rad/s)."""
    out: Path = Path("runs/spin")
    """Folder of spin.png and spin.json."""
    progress: bool = True
    """Show a progress bar."""


def _named(entry: str) -> tuple[str, str]:
    """NAME=PATH -> (NAME, PATH); a bare name or path is its own name."""
    name, sep, path = entry.partition("=")
    return (name, path) if sep and name and path else (entry, entry)


def spins_of(policy: str, cfg: Config, bar=None) -> np.ndarray:
    """Spin (rad/s about the commanded axis) of every in-hand step of ``cfg.episodes`` episodes."""
    from envs.config import Perturbation
    from envs.core import RotateCupVec
    from rotation.bundles import load_bundle
    from rotation.evaluate.job import Config as EvalConfig
    from rotation.evaluate.job import env_config

    bundle = load_bundle(policy)
    env_cfg = env_config(EvalConfig(episode_steps=cfg.episode_steps), bundle, Perturbation())
    env = RotateCupVec(env_cfg, num_envs=cfg.episodes)
    obs = env.reset(seed=cfg.seed)
    alive, spins = np.ones(cfg.episodes, dtype=bool), []
    for _ in range(cfg.episode_steps):
        actions = bundle.act_batch({k: obs[k] for k in bundle.config.obs_groups})
        actions[~alive] = 0.0
        obs, _, terminated, truncated, info = env.step(actions)
        spins.append((np.asarray(info["rotation"]) / env_cfg.control_dt)[alive])
        alive &= ~(terminated | truncated)
        if bar is not None:
            bar.update(1)
        if not alive.any():
            break
    return np.concatenate(spins)


def summarize(spin: np.ndarray, cfg: Config) -> dict[str, float]:
    clipped = np.clip(spin, -cfg.rotate_back_clip, cfg.rotate_clip)
    return {"steps": int(spin.size), "mean_spin": round(float(spin.mean()), 4),
            "mean_clipped": round(float(clipped.mean()), 4),
            "frac_above_clip": round(float((spin > cfg.rotate_clip).mean()), 4),
            "frac_below_back_clip": round(float((spin < -cfg.rotate_back_clip).mean()), 4),
            "p1": round(float(np.percentile(spin, 1)), 3), "p99": round(float(np.percentile(spin, 99)), 3)}


def run(cfg: Config) -> dict:
    if not cfg.policies:
        raise ValueError("policies: give at least one policy bundle")
    if cfg.episodes < 1 or cfg.episode_steps < 1:
        raise ValueError(f"episodes and episode_steps must be >= 1, got {cfg.episodes}, {cfg.episode_steps}")
    if not (cfg.rotate_clip > 0 and cfg.rotate_back_clip > 0):
        raise ValueError("rotate_clip and rotate_back_clip must be > 0")
    named = dict(_named(p) for p in cfg.policies)
    if len(named) != len(cfg.policies):
        raise ValueError(f"policies: two entries share a name: {list(cfg.policies)}")
    cfg.out.mkdir(parents=True, exist_ok=True)
    spins: dict[str, np.ndarray] = {}
    with tqdm(total=len(named) * cfg.episode_steps, desc="spin", unit="step", disable=not cfg.progress) as bar:
        for name, path in named.items():
            spins[name] = spins_of(path, cfg, bar)
    result = {name: summarize(s, cfg) for name, s in spins.items()}
    print(f"{'policy':<16} {'steps':>6} {'mean spin':>9} {'clipped':>8} {'>clip':>6} {'<-back':>6}  (rad/s)")
    for name, r in result.items():
        print(f"{name:<16} {r['steps']:>6} {r['mean_spin']:>9.3f} {r['mean_clipped']:>8.3f} "
              f"{r['frac_above_clip']:>6.2f} {r['frac_below_back_clip']:>6.2f}")
    fig, ax = plt.subplots(figsize=(6.4, 3.4))
    bins = np.linspace(-4.0, 3.0, 71)
    for i, (name, s) in enumerate(spins.items()):
        ax.hist(np.clip(s, bins[0], bins[-1]), bins=bins, density=True, histtype="step", lw=1.5, color=f"C{i}",
                label=f"{name}: mean {result[name]['mean_spin']:.2f}, clipped {result[name]['mean_clipped']:.2f}")
    for x in (-cfg.rotate_back_clip, cfg.rotate_clip):
        ax.axvline(x, color="0.4", ls="--", lw=0.8)
    ax.set_xlabel("spin per policy step about the commanded axis (rad/s; dashed: reward clips)")
    ax.set_ylabel("density")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(cfg.out / "spin.png", dpi=110)
    plt.close(fig)
    (cfg.out / "spin.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
