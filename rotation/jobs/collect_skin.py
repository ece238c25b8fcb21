"""The skin side of `rotate collect`: Xela streams, the scripted cup play, and the joystick task.

With ``--skin`` a session holds, beside the joint streams (control rate) and the object labels (cup task), every
100 Hz skin sample of the Xela hand (docs/skin.md):

- ``skin/xela`` (368, 3) raw counts, ``skin/taxel_pos`` (368, 3) taxel positions (m, hand frame) at each sample;
- ``labels/skin_force`` (18, 3) per pad [normal, shear x, shear y] (N, pad frame), at the same 100 Hz;
- ``labels/joystick`` (3,) roll, pitch, yaw (rad) of the stick, 100 Hz (joystick task);
- ``extra["skin"]``: the static taxel facts (envs.sensors.xela.skin_metadata: pad names, taxels per pad, taxel
  types).

``--policy play`` on the cup is a scripted play for skin pretraining data: the grip tightens and loosens in cycles
around the episode's grasp while the fingers sweep slowly, so contacts press, slide and release (the cup may drop:
the episode then ends, as with any policy).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from tqdm import tqdm

from envs import constants as C
from envs.core import RotateCupVec
from envs.grasps import FLEX_JOINTS
from envs.joystick import JoystickConfig, JoystickPlay
from envs.sensors.skin_obs import SkinState
from envs.sensors.xela import SAMPLE_HZ, skin_metadata
from rotation.configs import to_jsonable
from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter

SKIN_STREAMS = ("skin/xela", "skin/taxel_pos")
"""Streams at the skin's fixed 100 Hz."""


def joystick_streams(control_hz: float = JoystickConfig().control_hz) -> list[StreamSetup]:
    """The streams of a joystick session: joints per control step, then the skin and the stick's angles."""
    joints = [StreamSetup(n, rate_hz=control_hz) for n in ("joints/position", "joints/target", "joints/torque")]
    return joints + skin_streams(joystick=True)


def skin_streams(joystick: bool = False) -> list[StreamSetup]:
    """Skin streams and their labels (100 Hz); the joystick's angles with ``joystick``."""
    s = [StreamSetup(n) for n in SKIN_STREAMS] + [StreamSetup("labels/skin_force", rate_hz=SAMPLE_HZ)]
    if joystick:
        s.append(StreamSetup("labels/joystick", rate_hz=SAMPLE_HZ))
    return s


def record_skin(w: SessionWriter, skin: SkinState, i: int, extra: dict[str, np.ndarray] | None = None) -> None:
    """Append env ``i``'s skin samples of the last policy step (and ``extra`` label streams (N, S, ...))."""
    t = skin.last_times[i]
    w.append("skin/xela", skin.last_counts[i], t)
    w.append("skin/taxel_pos", skin.last_pos[i], t)
    w.append("labels/skin_force", skin.last_force[i], t)
    for name, value in (extra or {}).items():
        w.append(name, value[i], t)


class PlayPolicy:
    """Scripted cup play: grip cycles and slow finger sweeps around the episode's grasp, as env actions."""

    def __init__(self, num_envs: int, seed: int):
        self.seed = seed
        self.env: RotateCupVec | None = None
        self.motion = np.zeros((num_envs, 5, C.NUM_JOINTS))  # amplitude, frequency, phase, grip period, grip phase

    def bind(self, env: RotateCupVec) -> None:
        self.env = env

    def start(self, slot: int, episode: int) -> None:
        rng = np.random.default_rng([self.seed, episode, 0x504C4159])
        m = self.motion[slot]
        m[0] = rng.uniform(0.01, 0.06, C.NUM_JOINTS)  # sweep amplitude (rad)
        m[1] = rng.uniform(0.1, 0.6, C.NUM_JOINTS)  # sweep frequency (Hz)
        m[2] = rng.uniform(0.0, 2 * math.pi, C.NUM_JOINTS)
        m[3] = rng.uniform(1.5, 4.0)  # grip period (s)
        m[4] = rng.uniform(0.0, 2 * math.pi)

    def __call__(self, obs: dict, active: np.ndarray) -> np.ndarray:
        env = self.env
        t = (env.steps + 1) * env.cfg.control_dt  # (N,)
        m = self.motion
        flex = np.isin(np.arange(C.NUM_JOINTS), FLEX_JOINTS)
        # grip from -0.03 rad (loosened) to +0.2 rad (squeezed) on the flexion joints
        grip = -0.03 + 0.23 * (0.5 - 0.5 * np.cos(2 * math.pi * t / m[:, 3, 0] + m[:, 4, 0]))
        sweep = m[:, 0] * np.sin(2 * math.pi * m[:, 1] * t[:, None] + m[:, 2])
        desired = env.grasp_q + grip[:, None] * flex + sweep
        return np.clip((desired - env.targets) / env.cfg.action_scale, -1.0, 1.0) * active[:, None]


class _JoystickRecorder:
    """Writes one slot's joystick episode: joints per control step, skin and stick angles per skin sample."""

    def __init__(self, play: JoystickPlay, cfg: Any, slot: int, episode: int, path: Any, tags: dict[str, Any]):
        self.play, self.slot = play, slot
        jc = play.cfg
        meta = SessionMeta(
            source="sim", object="joystick", control_hz=jc.control_hz, seed=cfg.seed,
            properties={"spring": jc.spring, "damping": jc.damping, "max_tilt": jc.max_tilt},
            extra={"episode": episode, "slot": slot, "task": "joystick", "hand": "xela",
                   "skin_key": int(play.skin.skin.keys[slot]), "physics_dt": jc.physics_dt, "skin": skin_metadata(),
                   "collect": to_jsonable(cfg), **tags},
        )
        self.writer = SessionWriter(path, meta, joystick_streams(jc.control_hz), flush_interval_s=cfg.flush_interval_s,
                                    overwrite=True)

    def record_step(self, samples: bool) -> None:
        p, i, w = self.play, self.slot, self.writer
        t = np.array([p.steps[i] * p.cfg.control_dt])
        q, tau = p.joints()
        w.append("joints/position", q[i : i + 1], t)
        w.append("joints/target", p.targets[i : i + 1], t)
        w.append("joints/torque", tau[i : i + 1], t)
        if samples:
            record_skin(w, p.skin, i, {"labels/joystick": p.last_angles})

    def close(self) -> None:
        self.writer.close()


def run_joystick(cfg: Any, todo: list[int], path_of: Any, tags: dict[str, Any]) -> dict[str, float]:
    """Record the joystick episodes ``todo`` (episode e in slot e % num_envs, as its (e // num_envs)-th); ``tags``
    go into every session's ``extra`` (the collection's settings digest)."""
    m = cfg.num_envs
    play = JoystickPlay(JoystickConfig(motion="play" if cfg.policy == "play" else "random"), num_envs=m,
                        seed=cfg.seed)
    queues = [[e for e in todo if e % m == i] for i in range(m)]
    recorders: list[_JoystickRecorder | None] = [None] * m

    def start(slot: int) -> None:
        e = queues[slot].pop(0)
        play.episode[slot] = e // m - 1  # reset increments it
        play.reset(np.array([slot]))
        recorders[slot] = _JoystickRecorder(play, cfg, slot, e, path_of(cfg.out, e), tags)
        recorders[slot].record_step(samples=False)  # the state at t = 0

    for i in range(m):
        if queues[i]:
            start(i)
    steps, t0 = 0, time.perf_counter()
    try:
        with tqdm(total=len(todo), unit="episode", desc="collect joystick", disable=not cfg.progress,
                  dynamic_ncols=True) as bar:
            while any(r is not None for r in recorders):
                play.step()
                for i, r in enumerate(recorders):
                    if r is None:
                        continue
                    r.record_step(samples=True)
                    steps += 1
                    if play.steps[i] >= cfg.episode_steps:
                        r.close()
                        recorders[i] = None
                        bar.update(1)
                        if queues[i]:
                            start(i)
    finally:
        for r in recorders:  # interrupted: keep what was recorded, unmarked, for the next run to redo
            if r is not None:
                r.writer.abort()
    elapsed = time.perf_counter() - t0
    samples = steps * play.cfg.substeps
    print(f"collect: {len(todo)} joystick sessions, {steps} steps in {elapsed:.1f} s -> {cfg.out}")
    return {"episodes": len(todo), "steps": steps, "steps_per_s": steps / elapsed, "samples_per_s": samples / elapsed}
