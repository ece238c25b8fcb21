"""`rotate collect --task shake|oas`: the touch benchmarks' sessions, one per scripted episode, with every fingertip's
contact fields at the physics rate (the loader renders the four Digit 360 streams from them) and the labels the
benchmark probes.

- ``shake`` (envs.shake): the hand shakes closed bottles of pills, rice, lentils, water or oil at three fill levels.
  Labels ``content`` (class id, envs.shake_contents.CONTENT_NAMES), ``fill`` (FILL_LEVELS), ``content_mass`` (kg).
- ``oas`` (envs.oas): the hand taps, presses, slides or rotates a held object of one of four materials against a
  flat, ridged or rough surface. Labels ``object`` (envs.oas.OBJECTS), ``action`` (ACTIONS), ``surface``
  (SURFACES), and ``surface_force`` (N, the object's normal force on the surface, every physics step).

Episode e of a collection seeded s is the task's episode seeded ``s * 1_000_000 + e``: every label is drawn
uniformly, as are the object's size (a grasp bucket of the hand's cup grasps), the grasp and the motion. The class
labels are written at the control rate; the session's properties record the draws and whether the hand held the
object to the end (``held``; a probe leaves out the sessions where it did not).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from envs.constants import FINGERS
from envs.grasp_cache import load_default_cache
from envs.rng import splitmix64
from envs.scene import touch_model
from rotation.configs import to_jsonable
from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter

CONTROL_HZ = 20.0
"""Rate of the class label streams (the other tasks' control rate)."""
TASK_LABELS = {"shake": ("content", "fill", "content_mass"), "oas": ("object", "action", "surface")}
"""The constant labels of each task's sessions."""
PHYSICS_HZ = 500.0
"""Both tasks step at 2 ms."""


def bench_seed(seed: int, episode: int) -> int:
    """The task's seed of episode ``episode`` of a collection seeded ``seed``."""
    return int(seed) * 1_000_000 + int(episode)


def bench_streams(task: str) -> list[StreamSetup]:
    streams = [StreamSetup(f"labels/{name}", rate_hz=CONTROL_HZ) for name in TASK_LABELS[task]]
    if task == "oas":
        streams.append(StreamSetup("labels/surface_force", rate_hz=PHYSICS_HZ))
    return streams + [StreamSetup(f"digit360/{f}/contact", rate_hz=PHYSICS_HZ) for f in FINGERS]


def _simulate(task: str, hand: str, duration_s: float, seed: int, grasps: Any, grip: str = "palm",
              motion: str = "sine") -> tuple[Any, Any, dict, dict]:
    """(episode, recording, labels {name: value}, properties) of one episode (``grip``, ``motion``: how a shaken
    bottle is held and moved, envs.shake.ShakeConfig)."""
    if task == "shake":
        from envs.shake import ShakeConfig, ShakeSim, draw_episode
        from envs.shake_contents import FILL_LEVELS

        cfg = ShakeConfig(hand=hand, duration_s=duration_s, grip=grip, motion=motion)
        ep = draw_episode(cfg, seed, grasps)
        rec = ShakeSim(cfg, ep, grasps).run()
        labels = {"content": ep.content_id, "fill": ep.fill, "content_mass": rec.content_mass}
        props = {"content": ep.content, "fill": FILL_LEVELS[ep.fill], "content_mass": rec.content_mass,
                 "amplitude": ep.amplitude, "frequency": ep.frequency, "tilt": ep.tilt, "grip": grip,
                 "motion": motion}
        return ep, rec, labels, props
    from envs.oas import OasConfig, OasSim, draw_episode

    cfg = OasConfig(hand=hand, duration_s=duration_s)
    ep = draw_episode(cfg, seed, grasps)
    rec = OasSim(cfg, ep, grasps).run()
    props = {"object": ep.object, "action": ep.action, "surface": ep.surface, "depth": ep.depth,
             "frequency": ep.frequency, "extent": ep.extent}
    return ep, rec, dict(ep.labels), props


def record_episode(cfg: Any, hand: str, episode: int, path: Path, grasps: Any, tags: dict[str, Any]) -> bool:
    """Simulate and write episode ``episode`` of task ``cfg.task``; returns whether the hand held the object."""
    seed = bench_seed(cfg.seed, episode)
    ep, rec, labels, props = _simulate(cfg.task, hand, cfg.shake_s, seed, grasps, cfg.shake_grip, cfg.shake_motion)
    with np.errstate(over="ignore"):
        key = int(splitmix64(np.asarray([seed], dtype=np.uint64))[0])
    meta = SessionMeta(
        source="sim", object="bottle" if cfg.task == "shake" else ep.object, control_hz=CONTROL_HZ, seed=seed,
        properties={**props, "held": rec.held, "scale": float(grasps.scales[ep.bucket])},
        extra={"episode": episode, "task": cfg.task, "touch_key": key, "sim_hand": hand,
               "touch_generation": touch_model(hand).generation, "physics_dt": 1.0 / PHYSICS_HZ,
               cfg.task: to_jsonable(ep), "collect": to_jsonable(cfg), **tags},
    )
    with SessionWriter(path, meta, bench_streams(cfg.task), flush_interval_s=cfg.flush_interval_s,
                       overwrite=True) as w:
        t = np.arange(0.0, rec.times[-1] + 1e-9, 1.0 / CONTROL_HZ)
        for name, value in labels.items():
            w.append(f"labels/{name}", np.full((len(t), 1), float(value)), t)
        if cfg.task == "oas":
            w.append("labels/surface_force", rec.surface_force[:, None], rec.times)
        for f, finger in enumerate(FINGERS):
            w.append(f"digit360/{finger}/contact", rec.contact[f], rec.times)
    return rec.held


def run_bench(cfg: Any, todo: list[int], path_of: Any, tags: dict[str, Any]) -> dict[str, float]:
    """Record the episodes ``todo`` of task ``cfg.task``; ``tags`` go into every session's ``extra`` (the
    settings digest)."""
    hand = cfg.hand if cfg.hand != "auto" else "digit360_v4"
    grasps = load_default_cache("cup", "", hand)
    held, t0 = 0, time.perf_counter()
    with tqdm(todo, unit="episode", desc=f"collect {cfg.task}", disable=not cfg.progress, dynamic_ncols=True) as bar:
        for e in bar:
            held += record_episode(cfg, hand, e, path_of(cfg.out, e), grasps, tags)
    elapsed = time.perf_counter() - t0
    seconds = len(todo) * cfg.shake_s
    # one sample = one fingertip window the loader can cut: 30 per simulated second and fingertip, after the first
    # window's 1.12 s of history
    windows = len(todo) * max(0.0, cfg.shake_s - 1.12) * 30.0 * len(FINGERS)
    print(f"collect: {len(todo)} {cfg.task} sessions ({held} held to the end), {seconds:.0f} simulated s in "
          f"{elapsed:.1f} s -> {cfg.out}")
    return {"episodes": len(todo), "held": held, "sim_s_per_s": seconds / elapsed, "samples_per_s": windows / elapsed}
