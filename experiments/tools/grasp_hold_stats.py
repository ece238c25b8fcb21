"""How steady are the grasps of a cache? The hold check (envs.grasps.HoldRule) of every grasp, as a histogram.

Each grasp is replayed as the env resets into it (joint targets = the grasp's joints) and held still for
``--seconds`` at the given friction and mass, no pushes; the figure is the worst tilt of the object during the hold.
A grasp passes where it stays under ``--max-tilt``. ``rotate grasps`` keeps only grasps that pass (its defaults are
this script's); caches generated before that, or with ``--hold-seconds 0``, hold grasps that do not.

    python experiments/tools/grasp_hold_stats.py --caches cup before=old/grasps_cup.npz --out runs/grasp_hold
    python experiments/tools/grasp_hold_stats.py --caches cup --surface 0.25 --out runs/grasp_hold_slippery

``--surface`` scales the friction of the domes and of the links together, as `rotate evaluate`'s friction conditions
do (friction_0.25: ``--surface 0.25``): which grasps still hold a slippery cup by themselves.

Writes OUT/hold_tilt.png (one histogram per cache) and OUT/hold_stats.json; the last line printed is the same JSON.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from envs.grasp_cache import GraspCache, load_default_cache  # noqa: E402
from envs.grasps import HoldRule, hold_check  # noqa: E402
from envs.objects import OBJECTS  # noqa: E402
from envs.validation import check_number, check_output_dir  # noqa: E402
from rotation.configs import script_main  # noqa: E402


@dataclass
class Config:
    """Hold-check statistics settings."""

    caches: tuple[str, ...] = ("cup",)
    """Grasp caches: an object name (its shipped cache), a path to a .npz, or NAME=PATH."""
    seconds: float = HoldRule.seconds
    """Seconds of the hold."""
    friction: float | None = None
    """Friction of hand and object during the hold; default: the middle of the cache's hand's range
    (HoldRule.for_hand, as `rotate grasps` checks)."""
    mass: float | None = None
    """Object mass (kg) during the hold; default: the middle of the cache's hand's range."""
    max_tilt: float = HoldRule.max_tilt
    """A grasp passes where the object's worst tilt (rad) stays under this."""
    surface: float = 1.0
    """The cup surface's factor on the friction of the domes (``friction``) and of the links together, as an
    evaluation's friction condition applies it."""
    out: Path = Path("runs/grasp_hold")
    """Output directory."""

    def __post_init__(self) -> None:
        if not self.caches:
            raise ValueError("caches: name at least one cache")
        check_number("seconds", self.seconds, 0.0, 60.0, low_open=True, unit="s")
        if self.friction is not None:
            check_number("friction", self.friction, 0.01, 10.0)
        if self.mass is not None:
            check_number("mass", self.mass, 0.001, 5.0, unit="kg")
        check_number("max_tilt", self.max_tilt, 0.0, np.pi, low_open=True, unit="rad")
        check_number("surface", self.surface, 0.01, 10.0)
        self.out = Path(self.out)
        check_output_dir("out", self.out)


def _load(spec: str) -> tuple[str, GraspCache]:
    name, sep, path = spec.partition("=")
    if not sep:
        name = path = spec
    if not name or not path:
        raise ValueError(f"caches: {spec!r} is not NAME=PATH")
    return name, (load_default_cache(path) if path in OBJECTS else GraspCache.load(path))


def run(cfg: Config) -> dict:
    caches = [_load(spec) for spec in cfg.caches]  # every name checked before any work
    given = {k: v for k, v in (("friction", cfg.friction), ("mass", cfg.mass)) if v is not None}
    rules = {name: HoldRule.for_hand(cache.hand, seconds=cfg.seconds, max_tilt=cfg.max_tilt, surface=cfg.surface,
                                     **given)
             for name, cache in caches}
    stats, tilts = {}, {}
    for name, cache in caches:
        rule = rules[name]
        worst = hold_check(cache, rule)
        tilts[name] = worst
        passed = worst < rule.max_tilt
        stats[name] = {"object": cache.object, "grasps": int(worst.size), "pass": round(float(passed.mean()), 4),
                       "pass_per_scale": [round(float(x), 3) for x in passed.mean(1)],
                       "sank": round(float(np.isinf(worst).mean()), 4), "cache_hold_rule": list(cache.hold),
                       "rule": list(rule.as_array()), "surface": cfg.surface}
        print(f"{name}: {passed.mean():.1%} of {worst.size} grasps pass (sank: {np.isinf(worst).mean():.1%})")
    cfg.out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4))
    top = np.pi / 2
    bins = np.linspace(0, top, 46)
    for name, worst in tilts.items():
        ax.hist(np.minimum(worst.ravel(), top), bins=bins, histtype="step", lw=1.8,
                label=f"{name}: {stats[name]['pass']:.0%} pass")
    ax.axvline(rule.max_tilt, color="k", ls="--", lw=1, label=f"limit {np.degrees(rule.max_tilt):.0f} deg")
    ax.set_xlabel(f"worst tilt during a {rule.seconds:g} s hold (rad; sunk or past {top:.2f} piled at the right)")
    ax.set_ylabel("grasps")
    physics = {(r.friction, r.mass) for r in rules.values()}
    surface = f", cup surface x{cfg.surface:g}" if cfg.surface != 1.0 else ""
    ax.set_title("hand holding still, " + (f"friction {rule.friction:g}, mass {rule.mass:g} kg" if len(physics) == 1
                                           else "each cache at its hand's nominal friction and mass") + surface)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(cfg.out / "hold_tilt.png", dpi=110)
    plt.close(fig)
    result = {"rule": list(rule.as_array()) if len(physics) == 1 else None, "surface": cfg.surface, "caches": stats}
    (cfg.out / "hold_stats.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result))
    return result


def main(argv: list[str] | None = None) -> int:
    return script_main(Config, run, __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
