"""How far does a held cup creep under each contact setting? The shipped grasps held still, as the env resets into
them, for a few seconds: the object's sink (mm) and tilt, per setting of MuJoCo's contact model.

A cup held by silicone fingertips does not slide down a still hand; in simulation it does when the friction cone or
the constraint softness lets contacts slip a little every step (issue "The simulation is the real hand": 10.9 mm in
5 s with the env's pyramidal cones and impratio 3). Each setting compiles the env's model with its options
(envs.config.ContactConfig: cone, impratio, noslip iterations; the physics step; the contacts' time constant) and
replays every grasp of the nominal-scale bucket with the nominal friction and mass, no pushes, zero action.

    python experiments/tools/hold_creep.py --out runs/hold_creep                # every setting in SETTINGS
    python experiments/tools/hold_creep.py --settings today elliptic_10 --seconds 5 --out runs/hold_creep

Writes OUT/hold_creep.json and prints a table; the last line printed is the same JSON.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import mujoco
import mujoco.batch
import numpy as np

from envs import constants as C
from envs import task
from envs.config import ContactConfig, EnvConfig, RandomizationConfig
from envs.constants import DEFAULT_HAND
from envs.core import EpisodeStarts, task_model
from envs.geometry import tilt_angle
from envs.grasp_cache import load_default_cache
from envs.validation import check_number, check_output_dir
from rotation.configs import script_main

SETTINGS: dict[str, dict] = {
    "today": {"cone": "pyramidal", "impratio": 3.0},
    "pyramidal_10": {"cone": "pyramidal", "impratio": 10.0},
    "elliptic_3": {"cone": "elliptic", "impratio": 3.0},
    "elliptic_10": {"cone": "elliptic", "impratio": 10.0},
    "today_noslip": {"cone": "pyramidal", "impratio": 3.0, "noslip_iterations": 10},
    "elliptic_10_noslip": {"cone": "elliptic", "impratio": 10.0, "noslip_iterations": 10},
    "today_5ms": {"cone": "pyramidal", "impratio": 3.0, "physics_dt": 0.005},
    "elliptic_10_5ms": {"cone": "elliptic", "impratio": 10.0, "physics_dt": 0.005},
    "elliptic_10_noslip_5ms": {"cone": "elliptic", "impratio": 10.0, "noslip_iterations": 10, "physics_dt": 0.005},
    "today_5ms_stiff": {"cone": "pyramidal", "impratio": 3.0, "physics_dt": 0.005, "timeconst": 0.01},
    "elliptic_10_5ms_stiff": {"cone": "elliptic", "impratio": 10.0, "physics_dt": 0.005, "timeconst": 0.01},
    "hand": {},
}
"""Contact settings compared: MuJoCo's friction cone, the ratio of frictional to normal constraint impedance, the
noslip post-solver's iterations (0 = off), the physics step (s) and the contacts' time constant (s; the model's is
0.02, the stiffest MuJoCo honours at a 10 ms step: it needs at least two steps). 'hand' is the hand's own physics
(envs.physics.HAND_PHYSICS) at its nominal values: on the digit360_v4 hand the tips' and the links' frictions
apart, joint friction, torque scale, the contact model it trains with."""


@dataclass
class Config:
    out: Path = Path("runs/hold_creep")
    """Report directory."""
    settings: tuple[str, ...] = tuple(SETTINGS)
    """Settings to compare (names of SETTINGS)."""
    seconds: float = 5.0
    """How long each grasp is held still (s)."""
    object: str = "cup"
    """Object whose shipped grasp cache is replayed (its nominal-scale bucket)."""
    hand: str = DEFAULT_HAND
    """Hand variant (envs.scene.HANDS) whose model and grasp cache are used."""
    grasp_cache: str = ""
    """Grasp cache to replay (empty: the one shipped for the object and hand)."""
    settle: float = 0.0
    """Seconds held before the sink is measured from: a grasp found under other physics first settles into this
    one's equilibrium (a step down, then still), which is not creep."""

    def __post_init__(self) -> None:
        unknown = [s for s in self.settings if s not in SETTINGS]
        if unknown or not self.settings:
            raise ValueError(f"settings: unknown {unknown or 'none given'}; choose from {', '.join(SETTINGS)}")
        check_number("seconds", self.seconds, 0.1, 60.0, unit="s")


def _edit(setting: dict):
    """The settings EnvConfig has no field for: the contacts' time constant, on every geom."""

    def edit(spec: mujoco.MjSpec) -> None:
        if "timeconst" in setting:
            for geom in spec.geoms:
                geom.solref = [setting["timeconst"], 1.0]

    return edit


def hold(setting: dict, object_name: str, seconds: float, hand: str = DEFAULT_HAND, grasp_cache: str = "",
         limit: int | None = None, settle: float = 0.0) -> dict[str, float]:
    """Replay the nominal bucket's grasps (the first ``limit`` of them) under ``setting``: the sink (mm) and tilt
    (deg) over ``seconds`` after the first ``settle`` seconds. An empty setting is the hand's own physics at its
    nominal values."""
    contact = (ContactConfig(cone=setting["cone"], impratio=setting["impratio"],
                             noslip_iterations=setting.get("noslip_iterations", 0)) if setting else None)
    cfg = EnvConfig(object=object_name, physics_dt=setting.get("physics_dt", 0.01), contact=contact, hand=hand)
    model, obj, max_scale = task_model(cfg, edit=_edit(setting))
    cache = load_default_cache(object_name, grasp_cache, hand=hand)
    nominal = float(cfg.randomization.scales[len(cfg.randomization.scales) // 2])
    bucket = int(np.abs(cache.scales - nominal).argmin())
    rows = np.asarray(cache.grasps[bucket][:limit], dtype=np.float64)
    n = len(rows)
    batch = mujoco.batch.Batch(model, n, 0, persistent=True)
    starts = EpisodeStarts(batch, model, obj, max_scale)
    rc = cfg.randomization if not setting else RandomizationConfig()
    params = {"friction": np.full(n, float(np.mean(rc.friction))), "mass": np.full(n, float(np.mean(rc.mass))),
              "com": np.zeros((n, 3)), "kp": np.full((n, C.NUM_JOINTS), cfg.kp),
              "kd": np.full((n, C.NUM_JOINTS), cfg.kd), "scale": np.full(n, float(cache.scales[bucket]))}
    if not setting:  # its other parameters at the middle of their ranges
        params.update(task.nominal_hardware_params(cfg, n))
    ids = np.arange(n)
    starts.start(ids, params, rows[:, : C.NUM_JOINTS], rows[:, C.NUM_JOINTS :])
    o = starts.obj_qpos
    for _ in range(round(settle * cfg.control_hz)):
        batch.step(nstep=cfg.substeps)
    z0 = starts.qpos[:, o + 2].copy()
    t0 = time.perf_counter()
    for _ in range(max(1, round(seconds * cfg.control_hz))):
        batch.step(nstep=cfg.substeps)
    wall = time.perf_counter() - t0
    pose = starts.qpos[:, o : o + 7]
    sink = 1000 * (z0 - pose[:, 2])
    tilt = np.degrees(tilt_angle(pose[:, 3:]))
    return {"grasps": n, "sink_mm_median": float(np.median(sink)), "sink_mm_p90": float(np.percentile(sink, 90)),
            "sink_mm_max": float(np.max(sink)), "tilt_deg_median": float(np.median(tilt)),
            "dropped": int(np.sum(sink > 20)), "wall_s_per_sim_s": wall / seconds / n}


def run(cfg: Config) -> dict:
    check_output_dir("out", cfg.out)
    out = Path(cfg.out)
    rows = {}
    print(f"{'setting':22s} {'sink med':>9s} {'p90':>7s} {'max':>7s} {'tilt':>6s} {'drops':>6s}  (mm, deg; "
          f"{cfg.seconds:g} s held)")
    for name in cfg.settings:
        r = hold(SETTINGS[name], cfg.object, cfg.seconds, cfg.hand, cfg.grasp_cache, settle=cfg.settle)
        rows[name] = {**SETTINGS[name], **r}
        print(f"{name:22s} {r['sink_mm_median']:9.2f} {r['sink_mm_p90']:7.2f} {r['sink_mm_max']:7.2f} "
              f"{r['tilt_deg_median']:6.1f} {r['dropped']:6d}")
    report = {"object": cfg.object, "hand": cfg.hand, "seconds": cfg.seconds, "settle": cfg.settle,
              "grasp_cache": cfg.grasp_cache, "settings": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / "hold_creep.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    raise SystemExit(script_main(Config, run, __doc__))
