"""Collect simulated touch sessions: the batched env with Digit 360 touch (or the Xela skin) on, one file per episode.

    rotate collect --policy random --episodes 64 --out data/touch --num-envs 8
    rotate collect --policy runs/teacher/bundle --episodes 200 --out data/touch_lowfric --friction-scale 0.5
    rotate collect --policy student --episodes 20 --out data/heavy --added-mass 0.1 --com-shift 0 0 0.01
    rotate collect --skin --policy play --episodes 64 --out data/skin_cup        # Xela skin, scripted cup play
    rotate collect --skin --task joystick --policy play --episodes 64 --out data/skin_joystick
    rotate collect --task shake --episodes 200 --out data/shake               # bottles of pills, rice, ..., water
    rotate collect --task oas --episodes 200 --out data/oas                   # objects, actions, surfaces

Files: OUT/shard_<e // 100>/episode_<e>.h5 in the session format (rotation.data.session) with joint streams,
per-substep contact fields of every fingertip (the loader renders images, audio, IMU and pressure from them) and
per-step labels (force, slip, contact, object pose, privileged vector; the teacher's latent z when the policy is a
privileged bundle). With --skin the hand is the Xela variant and sessions hold the skin streams and labels instead
of the Digit 360 ones (rotation.jobs.collect_skin, docs/skin.md); --task joystick records the hand playing with the
joystick fixture (envs.joystick). OUT/collect.json records the settings. Episode e runs in env slot e % num_envs
as that slot's (e // num_envs)-th episode, so a run is deterministic under its settings and an interrupted run
resumes where it stopped: its complete files are kept, partial ones (a killed writer) are recorded again,
identically. A resume keeps only what this collection wrote (each session carries the settings' digest and its
episode index: rotation.jobs.collect_resume); any other file at an episode's path is refused, not overwritten.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from tqdm import tqdm

from envs import constants as C
from envs.config import EnvConfig, Perturbation
from envs.core import RotateCupVec
from envs.errors import RequestRefused
from envs.sensors.digit360 import FIELD, FINGERS, contact_frame_force, contact_slip, slot_values
from envs.sensors.xela import skin_metadata
from envs.validation import check_int, check_number, check_output_dir, check_seed, check_types
from rotation.configs import to_jsonable
from rotation.data.session import LATENT_DIM, SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter
from rotation.jobs.collect_bench import bench_streams, run_bench
from rotation.jobs.collect_resume import (
    SETTINGS,
    SETTINGS_KEY,
    SKIN_SETTINGS,
    check_manifest,
    kept_episode,
    settings_digest,
    write_manifest,
)
from rotation.jobs.collect_skin import PlayPolicy, joystick_streams, record_skin, run_joystick, skin_streams

SHARD_SIZE = 100
"""Episodes per shard directory."""


@dataclass(frozen=True)
class Config:
    policy: str = "random"
    """'random' (smoothed uniform actions), 'play' (scripted grip cycles and finger sweeps, for skin pretraining),
    or a policy bundle: a shipped name or a directory (load_bundle)."""
    episodes: int = 8
    """Number of episodes (= session files) to have in OUT when done."""
    out: Path = Path("touch_sessions")
    """Output directory (created; resumed if it already holds a collection with the same settings)."""
    friction_scale: float = 1.0
    """Multiplies the randomized friction (evaluation perturbation)."""
    added_mass: float = 0.0
    """Added object mass (kg)."""
    com_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Added centre-of-mass offset (m, object frame)."""
    num_envs: int = 4
    """Simulations stepped together."""
    seed: int = 0
    """Seed of the collection (env slot i is seeded seed + i)."""
    object: str = "cup"
    """Object to rotate (envs.objects)."""
    episode_steps: int = 400
    """Truncate episodes after this many policy steps (20 s at 20 Hz)."""
    random_scale: float = 0.5
    """Action magnitude of the random policy (actions in [-1, 1] x this, low-pass filtered)."""
    flush_interval_s: float = 2.0
    """Session writers flush at least this often (s): the most a crash can lose."""
    progress: bool = True
    """Show a progress bar."""
    skin: bool = False
    """Record the simulated Xela skin on the Xela hand (stock fingertips, 18 pads; docs/skin.md) instead of the
    Digit 360 fingertips: streams skin/xela, skin/taxel_pos, labels/skin_force at 100 Hz."""
    hand: Literal["auto", "digit360", "digit360_v4", "xela_v4"] = "auto"
    """The Digit 360 hand: 'auto' is a policy bundle's own hand, and 'digit360' for the scripted policies (the
    Xela hand with --skin); 'digit360_v4' (the vendor's kinematics, generation-2 touch: envs.scene.touch_model) for
    the scripted policies, or to check a bundle's hand. With --skin: 'auto' is the Xela hand of the first model
    ('xela'), 'xela_v4' the Xela skin on the vendor's kinematics (scripted cup play; the joystick fixture is built
    for the first model)."""
    task: Literal["cup", "joystick", "shake", "oas"] = "cup"
    """'cup': the RotateCup env with the object; 'joystick': the Xela hand presses and pushes the spring-returned
    joystick fixture (needs --skin and policy 'play' or 'random'; adds labels/joystick; the object and
    perturbation options do not apply); 'shake': the Digit 360 hand shakes closed bottles of pills, rice, lentils,
    water or oil by script; 'oas': it taps, presses, slides or rotates a held object of one of four materials on
    one of three surfaces (rotation.jobs.collect_bench: the touch benchmarks; their labels; the policy, object and
    perturbation options do not apply)."""
    shake_s: float = 3.0
    """Seconds per episode of --task shake or oas, the object's settling included."""
    shake_grip: Literal["palm", "fingertips"] = "palm"
    """How --task shake holds the bottle: 'palm' (the cup's grasps: the bottle rests on the phalanges and palm too)
    or 'fingertips' (on the four domes alone, squeezed: envs.plug_grip; the domes carry several times the force)."""
    shake_motion: Literal["sine", "strokes"] = "sine"
    """How --task shake moves the wrist: 'sine' or 'strokes' (constant speed, reversals at the shake's largest
    acceleration: the contents strike the wall at each; envs.shake.stroke)."""

    def __post_init__(self) -> None:
        check_types(self, skip=("com_shift",))  # Perturbation below checks com_shift with its own message
        if not self.policy:
            raise ValueError("policy: give 'random' or a policy bundle (shipped name or directory)")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        check_int("episodes", self.episodes, 1, 10**7)
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {self.num_envs}")
        check_int("num_envs", self.num_envs, 1, 4096)
        check_seed("seed", self.seed)
        if not 0.0 < self.random_scale <= 1.0:
            raise ValueError(f"random_scale must be in (0, 1], got {self.random_scale}")
        if not isinstance(self.com_shift, tuple | list) or len(self.com_shift) != 3:
            raise ValueError(f"com_shift needs 3 values (X Y Z, m), got {self.com_shift!r}")
        check_number("flush_interval_s", self.flush_interval_s, 0.0, 3600.0, low_open=True, unit="s")
        check_output_dir("out", self.out)
        if self.skin and self.hand not in ("auto", "xela_v4"):
            raise ValueError(f"hand: --skin records a Xela hand: leave --hand at auto or give xela_v4, got "
                             f"{self.hand!r}")
        if not self.skin and self.hand == "xela_v4":
            raise ValueError("hand: xela_v4 is the Xela skin's hand; add --skin")
        if self.task == "joystick" and self.hand == "xela_v4":
            raise ValueError("hand: the joystick fixture is built for the first Xela hand; leave --hand at auto")
        if self.task == "joystick" and not self.skin:
            raise ValueError("task: the joystick task records the Xela skin; add --skin")
        if self.task in ("shake", "oas") and (self.skin or self.hand == "digit360" or self.policy != "random"):
            raise ValueError(f"task: the {self.task} task moves the Digit 360 hand with the vendor's kinematics by "
                             "script; leave --skin, --hand and --policy out")
        check_number("shake_s", self.shake_s, 1.2, 600.0, unit="s (a Sparsh-X window needs 1.12 s of history)")
        for name, first in (("shake_grip", "palm"), ("shake_motion", "sine")):
            if getattr(self, name) != first and self.task != "shake":
                raise ValueError(f"{name}: only --task shake holds a bottle, got --task {self.task}")
        if self.task == "joystick" and self.policy not in ("play", "random"):
            raise ValueError(f"policy: the joystick task moves the hand by script: 'play' or 'random', got "
                             f"{self.policy!r}")
        # the object, the episode length and the perturbation as the env will see them (physical limits included)
        EnvConfig(object=self.object, episode_steps=self.episode_steps, **_sensors(self.skin, self.hand),
                  perturb=Perturbation(self.friction_scale, self.added_mass, tuple(self.com_shift)))


def _sensors(skin: bool, hand: str = "auto") -> dict[str, Any]:
    """The env's touch settings: Digit 360 fingertips (on ``hand`` unless 'auto'), or the Xela hand with its skin."""
    if skin:
        return dict(hand="xela_v4" if hand == "xela_v4" else "xela", skin=True, tactile=False)
    return dict(tactile=True) if hand == "auto" else dict(tactile=True, hand=hand)


def episode_path(out: Path, episode: int) -> Path:
    return out / f"shard_{episode // SHARD_SIZE:03d}" / f"episode_{episode:06d}.h5"


class _RandomPolicy:
    """Low-pass filtered uniform actions, a deterministic stream per episode (seed, episode)."""

    def __init__(self, num_envs: int, seed: int, scale: float):
        self.seed, self.scale = seed, scale
        self.rngs: list[np.random.Generator | None] = [None] * num_envs
        self.prev = np.zeros((num_envs, C.NUM_JOINTS))

    def start(self, slot: int, episode: int) -> None:
        self.rngs[slot] = np.random.default_rng([self.seed, episode])
        self.prev[slot] = 0.0

    def __call__(self, obs: dict, active: np.ndarray) -> np.ndarray:
        for i in np.flatnonzero(active):
            u = self.rngs[i].uniform(-1.0, 1.0, C.NUM_JOINTS)
            self.prev[i] = 0.7 * self.prev[i] + 0.3 * u  # smooth: a hand jerked at 20 Hz drops everything
        return np.clip(self.prev * self.scale / 0.3, -1.0, 1.0) * active[:, None]


class _BundlePolicy:
    """A policy bundle acting on the groups it reads (batched when the bundle offers ``act_batch``)."""

    def __init__(self, name_or_path: str):

        from rotation.bundles import load_bundle
        from rotation.policy.bundle import resolve_bundle
        from rotation.policy.bundle_config import WEIGHTS_FILE

        self.bundle = load_bundle(name_or_path)
        self.digest = hashlib.sha256((resolve_bundle(name_or_path) / WEIGHTS_FILE).read_bytes()).hexdigest()[:16]
        cfg = self.bundle.config
        self.groups = tuple(cfg.obs_groups)
        self.privileged = getattr(cfg, "latent_source", None) == "privileged" and cfg.latent_dim == LATENT_DIM

        self.cautious = self.bundle.start_correction(0) is not None
        self.steps: dict[int, int] = {}
        """Control steps each slot's episode has taken (a cautious start shifts the latent over the first ones)."""

    def start(self, slot: int, episode: int) -> None:
        self.steps[slot] = 0

    def _obs(self, obs: dict) -> dict:
        return {k: obs[k] for k in self.groups}

    def _start_corrections(self, n: int) -> np.ndarray | None:
        """(n, Z) cautious-start shifts of the slots at their own steps (zero past the start), or None: none."""
        if not self.cautious:
            return None
        rows = [self.bundle.start_correction(self.steps.get(i, 0)) for i in range(n)]
        if all(r is None for r in rows):
            return None
        zero = np.zeros(self.bundle.config.latent_dim, np.float32)
        return np.stack([zero if r is None else r for r in rows])

    def __call__(self, obs: dict, active: np.ndarray) -> np.ndarray:
        o = self._obs(obs)
        correction = self._start_corrections(len(active))
        for i in np.flatnonzero(active):
            self.steps[int(i)] = self.steps.get(int(i), 0) + 1
        if correction is not None:
            return np.asarray(self.bundle.act_batch(o, correction=correction), dtype=np.float64)
        if hasattr(self.bundle, "act_batch"):
            return np.asarray(self.bundle.act_batch(o), dtype=np.float64)
        return np.stack([self.bundle.act({k: v[i] for k, v in o.items()}) for i in range(len(active))])

    def latent(self, obs: dict) -> np.ndarray | None:
        """The teacher's z (N, 8) when the bundle is a privileged teacher, else None."""
        return np.asarray(self.bundle.latent(self._obs(obs)), dtype=np.float32) if self.privileged else None


def _streams(control_hz: float, physics_hz: float, with_z: bool, skin: bool = False) -> list[StreamSetup]:
    touch = () if skin else ("labels/force", "labels/contact_force", "labels/slip", "labels/contact")
    s = [StreamSetup(n, rate_hz=control_hz) for n in ("joints/position", "joints/target", "joints/torque", *touch,
                                                        "labels/object_pose", "labels/priv")]
    if with_z:
        s.append(StreamSetup("labels/z", rate_hz=control_hz))
    if skin:
        return s + skin_streams()
    s += [StreamSetup(f"digit360/{f}/contact", rate_hz=physics_hz) for f in FINGERS]
    return s


def _labels(rows: np.ndarray) -> dict[str, np.ndarray]:
    """Per-step touch labels from the last substep's contact fields (N, 4, D)."""
    return {
        "force": rows[..., [FIELD["force_n"], FIELD["force_x"], FIELD["force_y"]]].astype(np.float32),  # (N, 4, 3)
        "contact_force": contact_frame_force(rows),  # (N, 4, 2)
        "slip": contact_slip(rows).astype(np.float32),  # (N, 4)
        "contact": (slot_values(rows, "fn").max(axis=-1) > 0).astype(np.uint8),  # (N, 4)
    }


class _Recorder:
    """Writes one env slot's episode: joints and labels per policy step, contact fields per substep."""

    def __init__(self, env: RotateCupVec, cfg: Config, slot: int, episode: int, with_z: bool, digest: str):
        self.env, self.slot, self.episode = env, slot, episode
        self.path = episode_path(cfg.out, episode)
        p = env.params
        meta = SessionMeta(
            source="sim", object=cfg.object, control_hz=env.cfg.control_hz, seed=cfg.seed,
            properties={"scale": float(p["scale"][slot]), "mass": float(p["mass"][slot]),
                        "friction": float(p["friction"][slot]), "com": p["com"][slot].tolist()},
            extra={"episode": episode, "slot": slot, "physics_dt": env.cfg.physics_dt, "collect": to_jsonable(cfg),
                   SETTINGS_KEY: digest,
                   **({"hand": env.cfg.hand, "skin_key": int(env.skin.skin.keys[slot]), "skin": skin_metadata()}
                      if env.skin is not None else {"touch_key": int(env.touch.episode_keys[slot]),
                                                    "sim_hand": env.cfg.hand,
                                                    "touch_generation": env.touch.sensor.generation})},
        )
        streams = _streams(env.cfg.control_hz, 1.0 / env.cfg.physics_dt, with_z, env.skin is not None)
        self.writer = SessionWriter(self.path, meta, streams, flush_interval_s=cfg.flush_interval_s, overwrite=True)

    def record_step(self, obs: dict, z: np.ndarray | None, labels: dict[str, np.ndarray], substeps: bool) -> None:
        env, i, w = self.env, self.slot, self.writer
        t = np.array([env.steps[i] * env.cfg.control_dt])
        qpos = env.batch.bind("qpos")
        w.append("joints/position", qpos[i : i + 1, : C.NUM_JOINTS], t)
        w.append("joints/target", env.targets[i : i + 1], t)
        w.append("joints/torque", env.batch.bind("actuator_force")[i : i + 1], t)
        w.append("labels/object_pose", qpos[i : i + 1, env.obj_qpos : env.obj_qpos + 7], t)
        w.append("labels/priv", obs["priv"][i : i + 1], t)
        for name, value in labels.items():
            w.append(f"labels/{name}", value[i : i + 1], t)
        if z is not None:
            w.append("labels/z", z[i : i + 1], t)
        if substeps and env.skin is not None:
            record_skin(w, env.skin, i)
        elif substeps:
            for f, finger in enumerate(FINGERS):
                w.append(f"digit360/{finger}/contact", env.touch.last_rows[i, f], env.touch.last_times[i])

    def close(self) -> None:
        self.writer.close()


def _env_config(cfg: Config, policy: _RandomPolicy | _BundlePolicy) -> EnvConfig:
    """The collection's env; with a bundle, at the control rate and action scale it was trained at."""
    timing = {}
    sensors = _sensors(cfg.skin, cfg.hand)
    if isinstance(policy, _BundlePolicy):
        from rotation.bundles import check_policy_hand, policy_hand

        timing = dict(control_hz=policy.bundle.config.control_hz, action_scale=policy.bundle.config.action_scale)
        hand = sensors.get("hand", policy_hand(policy.bundle))
        check_policy_hand(f"--policy {cfg.policy}", policy.bundle, hand)
        if hand == "xela_v4" or (hand == "digit360_v4" and cfg.skin):  # (EnvConfig would say so less plainly)
            raise RequestRefused(f"--policy {cfg.policy} acts on the {hand} hand, whose "
                                 f"{'Xela skin' if cfg.skin else 'Digit 360 touch'} collect does not simulate yet; "
                                 "collect with a policy of the digit360, digit360_v4 or xela hand")
        sensors = {**sensors, "hand": hand}
    return EnvConfig(object=cfg.object, episode_steps=cfg.episode_steps, **sensors,
                     perturb=Perturbation(cfg.friction_scale, cfg.added_mass, tuple(cfg.com_shift)), **timing)


def _settings(cfg: Config, env_cfg: EnvConfig, policy: Any) -> dict[str, Any]:
    settings = {k: to_jsonable(getattr(cfg, k)) for k in (*SETTINGS, *SKIN_SETTINGS)}
    settings.update(control_hz=env_cfg.control_hz, action_scale=env_cfg.action_scale)
    if cfg.hand != "auto":  # recorded only when chosen, so that the digest of earlier collections stays theirs
        settings["hand"] = cfg.hand
    if isinstance(policy, _BundlePolicy):
        settings["policy_weights_sha256"] = policy.digest
    return settings


def run(cfg: Config) -> dict[str, float]:
    """Collect until OUT holds ``cfg.episodes`` complete sessions; returns simple throughput figures.

    Everything that can refuse the run (the policy bundle, the env settings, the grasp cache, an OUT holding other
    sessions) is checked before the manifest is written, so a refused run leaves nothing that refuses the corrected
    one."""
    m = cfg.num_envs
    scripted = {"random": lambda: _RandomPolicy(m, cfg.seed, cfg.random_scale), "play": lambda: PlayPolicy(m, cfg.seed)}
    policy = scripted[cfg.policy]() if cfg.policy in scripted else _BundlePolicy(cfg.policy)
    env_cfg = _env_config(cfg, policy)
    settings = _settings(cfg, env_cfg, policy)
    if cfg.task in ("shake", "oas"):
        settings["shake_s"] = cfg.shake_s
    if cfg.shake_grip != "palm":  # the first collections' settings (and digests) stay as they were
        settings["shake_grip"] = cfg.shake_grip
    if cfg.shake_motion != "sine":
        settings["shake_motion"] = cfg.shake_motion
    check_manifest(cfg, settings)
    digest = settings_digest(settings)
    with_z = isinstance(policy, _BundlePolicy) and policy.privileged
    if cfg.task == "joystick":
        streams = [s.name for s in joystick_streams()]
    elif cfg.task in ("shake", "oas"):
        streams = [s.name for s in bench_streams(cfg.task)]
    else:
        streams = [s.name for s in _streams(env_cfg.control_hz, 1.0 / env_cfg.physics_dt, with_z, cfg.skin)]
    todo = [e for e in range(cfg.episodes) if not kept_episode(episode_path(cfg.out, e), e, digest, streams)]
    if not todo:
        print(f"collect: {cfg.out} already holds {cfg.episodes} complete sessions")
        return {"episodes": 0, "steps": 0, "steps_per_s": 0.0, "samples_per_s": 0.0}
    if cfg.task == "joystick":
        write_manifest(cfg, settings)
        return run_joystick(cfg, todo, episode_path, {SETTINGS_KEY: digest})
    if cfg.task in ("shake", "oas"):
        write_manifest(cfg, settings)
        return run_bench(cfg, todo, episode_path, {SETTINGS_KEY: digest})
    env = RotateCupVec(env_cfg, num_envs=m, seed=cfg.seed)  # loads the grasp cache: may still refuse
    write_manifest(cfg, settings)
    if isinstance(policy, PlayPolicy):
        policy.bind(env)
    queues = [[e for e in todo if e % m == i] for i in range(m)]  # slot i runs episodes i, i + m, ...
    obs = env.reset(seed=cfg.seed)
    recorders: list[_Recorder | None] = [None] * m

    def start(slot: int) -> dict:
        """Start the slot's next queued episode (its (e // m)-th episode, whatever ran before)."""
        slot, e = int(slot), queues[slot].pop(0)
        env.episode[slot] = e // m - 1  # _reset_ids increments it: the env draws episode e // m of this slot
        new_obs = env.reset(ids=np.array([slot]))
        policy.start(slot, e)
        recorders[slot] = _Recorder(env, cfg, slot, e, with_z, digest)
        labels = _labels(env.touch.last_rows[:, :, -1]) if env.touch is not None else {}
        z = policy.latent(new_obs) if with_z else None
        recorders[slot].record_step(new_obs, z, labels, substeps=False)  # the state at t = 0
        return new_obs

    for i in range(m):
        if queues[i]:
            obs = start(i)
    steps, t0 = 0, time.perf_counter()
    try:
        with tqdm(total=len(todo), unit="episode", desc="collect", disable=not cfg.progress, dynamic_ncols=True) as bar:
            while any(r is not None for r in recorders):
                active = np.array([r is not None for r in recorders])
                actions = policy(obs, active)
                obs, _, terminated, truncated, _ = env.step(actions * active[:, None])
                steps += int(active.sum())
                labels = _labels(env.touch.last_rows[:, :, -1]) if env.touch is not None else {}
                z = policy.latent(obs) if with_z else None
                for i in np.flatnonzero(active):
                    recorders[i].record_step(obs, z, labels, substeps=True)
                for i in np.flatnonzero(active & (terminated | truncated)):
                    recorders[i].close()
                    recorders[i] = None
                    bar.update(1)
                    if queues[i]:
                        obs = start(i)
                bar.set_postfix(steps_per_s=f"{steps / (time.perf_counter() - t0):.0f}")
    finally:
        for r in recorders:  # interrupted: keep what was recorded, unmarked, for the next run to redo
            if r is not None:
                r.writer.abort()
    elapsed = time.perf_counter() - t0
    # one sample = one fingertip window the loader can cut: 30 per simulated second and fingertip (skin: one frame)
    samples = steps * (env_cfg.substeps if cfg.skin else env_cfg.control_dt * 30.0 * len(FINGERS))
    print(f"collect: {len(todo)} sessions, {steps} steps in {elapsed:.1f} s -> {cfg.out}")
    return {"episodes": len(todo), "steps": steps, "steps_per_s": steps / elapsed, "samples_per_s": samples / elapsed}
