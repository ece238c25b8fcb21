"""`rotate collect --task shake`: the hand shakes closed bottles of pills, rice, lentils, water or oil at three fill
levels (envs.shake); one session per episode with every fingertip's contact fields at the physics rate (the loader
renders the four Digit 360 streams from them) and the labels the shaking benchmark probes.

Episode e of a collection seeded s is envs.shake's episode seeded ``s * 1_000_000 + e``: its content and fill level
are drawn uniformly, as are its bottle size (a grasp bucket of the hand's cup grasps), grasp, and shake. Streams:
``digit360/<finger>/contact`` (500 Hz) and, at the control rate, ``labels/content`` (class id,
envs.shake_contents.CONTENT_NAMES), ``labels/fill`` (level id, FILL_LEVELS) and ``labels/content_mass`` (kg).
The session's properties record the draws, the content's mass and whether the hand held the bottle to the end
(``held``; a probe leaves out the sessions where it did not).
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
from envs.shake import TIMESTEP, ShakeConfig, ShakeSim, draw_episode
from envs.shake_contents import CONTENT_NAMES, FILL_LEVELS
from rotation.configs import to_jsonable
from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter

CONTROL_HZ = 20.0
"""Rate of the label streams (the other tasks' control rate)."""
SHAKE_LABELS = ("content", "fill", "content_mass")


def shake_seed(seed: int, episode: int) -> int:
    """envs.shake's seed of episode ``episode`` of a collection seeded ``seed``."""
    return int(seed) * 1_000_000 + int(episode)


def shake_streams() -> list[StreamSetup]:
    return ([StreamSetup(f"labels/{name}", rate_hz=CONTROL_HZ) for name in SHAKE_LABELS]
            + [StreamSetup(f"digit360/{f}/contact", rate_hz=1.0 / TIMESTEP) for f in FINGERS])


def record_episode(cfg: Any, shake: ShakeConfig, episode: int, path: Path, grasps: Any, tags: dict[str, Any]
                   ) -> bool:
    """Simulate and write episode ``episode``; returns whether the hand held the bottle."""
    ep = draw_episode(shake, shake_seed(cfg.seed, episode), grasps)
    rec = ShakeSim(shake, ep, grasps).run()
    with np.errstate(over="ignore"):
        key = int(splitmix64(np.asarray([ep.seed], dtype=np.uint64))[0])
    meta = SessionMeta(
        source="sim", object="bottle", control_hz=CONTROL_HZ, seed=ep.seed,
        properties={"content": ep.content, "fill": FILL_LEVELS[ep.fill], "content_mass": rec.content_mass,
                    "held": rec.held, "scale": float(grasps.scales[ep.bucket]), "amplitude": ep.amplitude,
                    "frequency": ep.frequency, "tilt": ep.tilt},
        extra={"episode": episode, "task": "shake", "touch_key": key, "sim_hand": shake.hand,
               "touch_generation": touch_model(shake.hand).generation, "physics_dt": TIMESTEP,
               "shake": to_jsonable(ep), "collect": to_jsonable(cfg), **tags},
    )
    with SessionWriter(path, meta, shake_streams(), flush_interval_s=cfg.flush_interval_s, overwrite=True) as w:
        t = np.arange(0.0, rec.times[-1] + 1e-9, 1.0 / CONTROL_HZ)
        for name, value in (("content", ep.content_id), ("fill", ep.fill), ("content_mass", rec.content_mass)):
            w.append(f"labels/{name}", np.full((len(t), 1), float(value)), t)
        for f, finger in enumerate(FINGERS):
            w.append(f"digit360/{finger}/contact", rec.contact[f], rec.times)
    return rec.held


def run_shake(cfg: Any, todo: list[int], path_of: Any, tags: dict[str, Any]) -> dict[str, float]:
    """Record the shaking episodes ``todo``; ``tags`` go into every session's ``extra`` (the settings digest)."""
    shake = ShakeConfig(hand=cfg.hand if cfg.hand != "auto" else "digit360_v4", duration_s=cfg.shake_s)
    grasps = load_default_cache("cup", "", shake.hand)
    held, t0 = 0, time.perf_counter()
    with tqdm(todo, unit="episode", desc="collect shake", disable=not cfg.progress, dynamic_ncols=True) as bar:
        for e in bar:
            held += record_episode(cfg, shake, e, path_of(cfg.out, e), grasps, tags)
    elapsed = time.perf_counter() - t0
    seconds = len(todo) * shake.duration_s
    # one sample = one fingertip window the loader can cut: 30 per simulated second and fingertip, after the first
    # window's history
    windows = len(todo) * max(0.0, shake.duration_s - 1.12) * 30.0 * len(FINGERS)
    print(f"collect: {len(todo)} shaking sessions ({held} held to the end; contents "
          f"{', '.join(CONTENT_NAMES)}), {seconds:.0f} simulated s in {elapsed:.1f} s -> {cfg.out}")
    return {"episodes": len(todo), "held": held, "sim_s_per_s": seconds / elapsed,
            "samples_per_s": windows / elapsed}
