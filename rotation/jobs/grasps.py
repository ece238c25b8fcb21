"""Generate initial grasps with Hora's acceptance rule and write a grasp cache per object.

For each object and each randomization scale bucket: sample the canonical closed pose + U(-noise, noise) per joint,
close the fingers on the floating object, release it under gravity for 50 policy steps, and keep the grasp if all
four fingertips are within 10 cm of the object, at least two touch it, it did not fall, and it stands upright
(its up axis within --max-tilt of vertical). Then the hold check: reset into the grasp as the env does (joint targets
= the grasp's joints), hold still for --hold-seconds at the nominal friction and mass, and keep the grasp only if the
object stays within --hold-tilt of vertical and does not sink (about a third of the grasps that pass the first rule
fail this one; `--hold-seconds 0` turns it off). `--hold-surface S` holds them on a cup surface of S times the
friction (the domes' and the links' together, as `rotate evaluate`'s friction conditions scale it): at 0.25 only
44% of the shipped cup grasps hold (experiments/teacher_v4, stage 11), and a cache of grasps that do starts every
policy from a grasp that keeps a slippery cup by itself.

    rotate grasps --objects cup cylinder --per-scale 100 --out grasps/
    rotate grasps --objects cup --hand xela --out grasps/      # the Xela skin hand (docs/skin.md)
    rotate grasps --objects cup --hold-surface 0.25 --out grasps_slippery/   # grasps that hold a slippery cup
    rotate view --object cup --grasp-cache grasps/grasps_cup.npz --out cup.png

The files are `OUT/grasps_<object>.npz` (`OUT/grasps_<object>_xela.npz` for the Xela hand); pass one to the env as
`grasp_cache=...` (or `--grasp-cache`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from tqdm import tqdm

from envs.config import RandomizationConfig, default_randomization
from envs.constants import DEFAULT_HAND
from envs.grasp_cache import default_cache_path
from envs.grasps import DEFAULT_MAX_TILT, HoldRule, generate_grasps
from envs.objects import OBJECTS, get_object
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types


@dataclass
class Config:
    objects: tuple[str, ...] = ("cup",)
    """Objects to generate grasps for (names in envs.objects.OBJECTS)."""
    scales: tuple[float, ...] | None = None
    """Scale buckets (the env picks the nearest bucket for each env's scale); default: the hand's randomization's
    (envs.physics.HAND_PHYSICS)."""
    per_scale: int = 100
    """Accepted grasps to keep per scale."""
    seed: int = 0
    """Seed of the pose sampling."""
    batch_size: int = 128
    """Candidate grasps simulated together."""
    noise: float = 0.25
    """Joint noise U(-noise, noise) rad around the canonical pose (Hora: 0.25)."""
    max_tilt: float = DEFAULT_MAX_TILT
    """Keep only grasps holding the object's up axis within this angle (rad) of vertical after settling."""
    out: Path = Path("grasps")
    """Output directory."""
    hold_seconds: float = HoldRule.seconds
    """Hold check: seconds the grasp must hold the object still by itself (0 turns the check off)."""
    hold_friction: float | None = None
    """Hold check: friction of the fingertips (of hand and object on a hand with one coefficient); default: the
    middle of the hand's randomization range."""
    hold_mass: float | None = None
    """Hold check: object mass in kg; default: the middle of the hand's randomization range."""
    hold_tilt: float = HoldRule.max_tilt
    """Hold check: the largest tilt (rad) the object may reach during the hold."""
    hold_surface: float = 1.0
    """Hold check: the cup surface's factor on the friction of the domes and of the links together (1: the hand's
    own materials)."""
    hand: Literal["digit360", "xela", "digit360_v4", "xela_v4"] = DEFAULT_HAND
    """Hand variant (envs.scene.HANDS): 'digit360' fingertips or the Xela skin hand; grasps are hand-specific."""

    def __post_init__(self) -> None:
        check_types(self)
        self.out = Path(self.out)
        if not self.objects:
            raise ValueError("objects: name at least one object")
        for name in self.objects:
            if name not in OBJECTS:
                raise ValueError(f"objects: unknown object {name!r}; known objects: {', '.join(sorted(OBJECTS))}")
        rule = HoldRule.for_hand(self.hand)
        if self.scales is None:
            self.scales = default_randomization(self.hand).scales
        if self.hold_friction is None:
            self.hold_friction = rule.friction
        if self.hold_mass is None:
            self.hold_mass = rule.mass
        try:
            RandomizationConfig(scales=tuple(self.scales))
        except ValueError as err:
            raise ValueError(f"scales: {err}") from None
        check_int("per_scale", self.per_scale, 1, 100_000)
        check_seed("seed", self.seed)
        check_int("batch_size", self.batch_size, 1, 65_536)
        check_number("noise", self.noise, 0.0, 1.0, unit="rad")
        check_number("max_tilt", self.max_tilt, 0.0, math.pi, low_open=True, unit="rad")
        check_number("hold_seconds", self.hold_seconds, 0.0, 60.0, unit="s")
        check_number("hold_friction", self.hold_friction, 0.01, 10.0)
        check_number("hold_mass", self.hold_mass, 0.001, 5.0, unit="kg")
        check_number("hold_tilt", self.hold_tilt, 0.0, math.pi, low_open=True, unit="rad")
        check_number("hold_surface", self.hold_surface, 0.01, 10.0, low_open=True)
        check_output_dir("out", self.out)

    @property
    def hold(self) -> HoldRule | None:
        if self.hold_seconds == 0:
            return None
        return HoldRule(self.hold_seconds, self.hold_friction, self.hold_mass, self.hold_tilt, self.hold_surface)


def run(cfg: Config) -> list[Path]:
    for name in cfg.objects:
        get_object(name)  # fail before any work on an unknown name
    if cfg.per_scale < 1 or cfg.batch_size < 1:
        raise ValueError(f"per_scale and batch_size must be >= 1, got {cfg.per_scale}, {cfg.batch_size}")
    RandomizationConfig(scales=tuple(cfg.scales or ()))  # validates the scales
    written = []
    for name in cfg.objects:
        start = time.time()
        done: dict[float, int] = {}
        # closed before a refusal reaches the user, so its line is the last one printed
        with tqdm(total=cfg.per_scale * len(cfg.scales), desc=f"grasps {name}", unit="grasp") as bar:

            def progress(scale: float, accepted: int, wanted: int, bar=bar, done=done) -> None:
                done[scale] = min(accepted, wanted)
                bar.n = sum(done.values())
                bar.refresh()

            cache = generate_grasps(name, tuple(cfg.scales), cfg.per_scale, seed=cfg.seed,
                                    batch_size=cfg.batch_size, noise=cfg.noise, progress=progress,
                                    max_tilt=cfg.max_tilt, hand=cfg.hand, hold=cfg.hold)
        path = cfg.out / default_cache_path(name, cfg.hand).name
        cache.save(path)
        written.append(path)
        print(f"{name}: {cache.grasps.shape[0]} scales x {cache.grasps.shape[1]} grasps -> {path} "
              f"({time.time() - start:.1f} s)")
    return written
