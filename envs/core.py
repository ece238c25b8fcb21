"""The batched RotateCup core: N MuJoCo simulations of one model on `mujoco.batch.Batch` threads.

One class does the whole task (randomization, actuation, reward, termination, observations) for N envs at once
with numpy; the gymnasium env is this core with N = 1, and the vector adapters wrap it without a per-env Python
loop. Env i of a batch seeded s behaves exactly like a single env seeded s + i (see envs.rng).
"""

from __future__ import annotations

import numbers
import os
import time
from functools import partial

import gymnasium as gym
import mujoco
import mujoco.batch
import numpy as np

from envs import constants as C
from envs import task
from envs.config import ContactConfig, EnvConfig
from envs.geometry import angular_velocity  # noqa: F401 (re-exported for rotation.deploy)
from envs.grasp_cache import GraspCache, load_default_cache
from envs.objects import ObjectSpec, get_object
from envs.observation import ProprioHistory
from envs.physics import object_friction
from envs.rng import CounterRNG, env_keys
from envs.scene import OBJECT_BODY, build_model, link_geoms, skin_geoms, touch_model
from envs.sensors.digit360 import add_digit360_sensors
from envs.sensors.skin_obs import SkinState, skin_space
from envs.sensors.tactile_obs import TouchState, tactile_space
from envs.sensors.xela_hand import add_xela_sensors
from envs.validation import check_int, check_seed

# Random streams (see envs.rng): one id per use, so adding a draw never shifts another.
_STREAM_RESET, _STREAM_NOISE, _STREAM_PUSH_P, _STREAM_PUSH_F, _STREAM_PHYS = 1, 2, 3, 4, 5
PUSH_DECAY_PERIOD = task.PUSH_DECAY_PERIOD
"""Hora decays pushes by `push_decay` every 0.08 s."""


def set_contact(m: mujoco.MjModel, contact: ContactConfig) -> None:
    """Write a contact model (envs.physics.ContactConfig) into ``m`` in place: cone, impratio, noslip iterations and,
    where set, every geom's time constant and impedance."""
    m.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC if contact.cone == "elliptic" else mujoco.mjtCone.mjCONE_PYRAMIDAL
    m.opt.impratio = contact.impratio
    m.opt.noslip_iterations = contact.noslip_iterations
    if contact.timeconst is not None:
        m.geom_solref[:, 0] = contact.timeconst
    if contact.solimp is not None:
        m.geom_solimp[:, :3] = contact.solimp


def set_torque_limits(m: mujoco.MjModel, cfg: EnvConfig) -> None:
    """The config's torque limits on every actuator: the vendor's per joint, or ``torque_limit`` on all."""
    if cfg.joint_torque_limits == "vendor":
        m.actuator_forcerange[:] = np.stack([-C.TORQUE_LIMITS, C.TORQUE_LIMITS], axis=1)
    else:
        m.actuator_forcerange[:] = [-cfg.torque_limit, cfg.torque_limit]


def task_model(cfg: EnvConfig, edit=None) -> tuple[mujoco.MjModel, ObjectSpec, float]:
    """The task's compiled model, shared by both physics backends: the hand and ``cfg.object`` at the largest scale
    the randomization may pick (smaller ones shrink geoms per simulation), the contact model's settings, the torque
    limit and the nominal PD gains.
    Returns (model, object spec, compiled scale)."""
    obj = get_object(cfg.object)
    rc = cfg.randomization
    max_scale = (max(rc.scales) + rc.scale_jitter) if rc.enabled else float(rc.scales[len(rc.scales) // 2])
    m = build_model(obj, max_scale, cfg.physics_dt, edit=edit, hand=cfg.hand)
    set_contact(m, cfg.contact)
    set_torque_limits(m, cfg)
    task.set_gains(m.actuator_gainprm[None], m.actuator_biasprm[None], np.full((1, C.NUM_JOINTS), cfg.kp),
                   np.full((1, C.NUM_JOINTS), cfg.kd))
    return m, obj, max_scale


class EpisodeStarts:
    """Places simulations of a batch of the task model at an episode start: their physical parameters (object scale,
    friction, mass, centre of mass, inertia, PD gains) and their start state (grasp joints, object pose, at rest).

    The env's reset and the grasp hold check (envs.grasps.HoldTest) both start episodes through it, so a grasp
    that passes the check starts the env's episodes the same way. It needs only the compiled model, not a grasp
    cache, so the check can run while an object's first cache is being generated."""

    def __init__(self, batch: mujoco.batch.Batch, model: mujoco.MjModel, obj: ObjectSpec, max_scale: float):
        self.batch, self.obj = batch, obj
        self.obj_body = model.body(OBJECT_BODY).id
        self.obj_geoms = np.flatnonzero(model.geom_bodyid == self.obj_body)
        self.obj_qpos = int(model.joint("object_free").qposadr[0])
        # object geometry at scale 1 (the model was compiled at max_scale)
        self.geom_size1 = model.geom_size[self.obj_geoms].copy() / max_scale
        self.geom_pos1 = model.geom_pos[self.obj_geoms].copy() / max_scale
        # per-simulation model fields written at each start
        self.geom_size, self.geom_pos = batch.expand("geom_size"), batch.expand("geom_pos")
        self.geom_friction = batch.expand("geom_friction")
        self.body_mass, self.body_ipos = batch.expand("body_mass"), batch.expand("body_ipos")
        self.body_inertia = batch.expand("body_inertia")
        self.gainprm, self.biasprm = batch.expand("actuator_gainprm"), batch.expand("actuator_biasprm")
        # the hardware physics (envs.physics): the skin and the rest of the hand, each with its own friction, and the
        # model fields its other draws write
        self.tip_geoms = skin_geoms(model)
        self.link_geoms = link_geoms(model, self.obj_geoms)
        self.forcerange0 = model.actuator_forcerange.copy()
        self.frictionloss0 = model.dof_frictionloss.copy()
        self.solref0 = model.geom_solref.copy()
        self.noslip0 = int(model.opt.noslip_iterations)
        self._fields: dict[str, np.ndarray] = {}
        # live state views
        self.qpos, self.qvel, self.ctrl = batch.bind("qpos"), batch.bind("qvel"), batch.bind("ctrl")
        self.xfrc = batch.bind("xfrc_applied")

    def _field(self, name: str) -> np.ndarray:
        """A per-simulation model field, given its own values on first use (the shipped physics never expands
        these, so its simulations stay as they were)."""
        if name not in self._fields:
            self._fields[name] = self.batch.expand(name)
        return self._fields[name]

    def _start_hardware_physics(self, ids: np.ndarray, p: dict[str, np.ndarray]) -> None:
        """Write the hardware physics' parameters of ``p`` (envs.task.sample_hardware_params) that are present."""
        if "torque_scale" in p:
            self._field("actuator_forcerange")[ids] = self.forcerange0[None] * p["torque_scale"][:, None, None]
        if "joint_friction" in p:
            loss = np.repeat(self.frictionloss0[None], len(ids), axis=0)
            loss[:, : C.NUM_JOINTS] = p["joint_friction"]
            self._field("dof_frictionloss")[ids] = loss
        if "impratio" in p:
            self._field("opt.impratio")[ids] = p["impratio"]
        if "timeconst" in p:
            solref = np.repeat(self.solref0[None], len(ids), axis=0)
            solref[:, :, 0] = p["timeconst"][:, None]
            self._field("geom_solref")[ids] = solref
        if "noslip" in p:
            self._field("opt.noslip_iterations")[ids] = np.where(p["noslip"] > 0, self.noslip0, 0)

    def start(self, ids: np.ndarray, p: dict[str, np.ndarray], q: np.ndarray, pose: np.ndarray) -> None:
        """Reset simulations ``ids`` (k,) with parameters ``p`` (scale, friction, mass (k,); com (k, 3); kp, kd
        (k, 16); and those of the hardware physics that its config sets, envs.task.PHYS_KEYS), joints and joint
        targets ``q`` (k, 16) and object pose ``pose`` (k, 7), at rest with no push."""
        self.batch.reset(ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        s = p["scale"][:, None, None]
        self.geom_size[np.ix_(ids, self.obj_geoms)] = self.geom_size1[None] * s
        self.geom_pos[np.ix_(ids, self.obj_geoms)] = self.geom_pos1[None] * s
        fr = self.geom_friction[ids]
        fr[:, :, 0] = p["friction"][:, None]  # one coefficient for hand and object (Hora); the floor never collides
        if "link_friction" in p:  # gel domes and the rest of the hand apart; the contact takes the larger (MuJoCo)
            fr[:, self.link_geoms, 0] = p["link_friction"][:, None]
            fr[:, self.obj_geoms, 0] = object_friction(p["friction"], p["link_friction"])[:, None]
        self.geom_friction[ids] = fr
        self.body_mass[ids, self.obj_body] = p["mass"]
        self.body_ipos[ids, self.obj_body] = p["com"]
        self.body_inertia[ids, self.obj_body] = task.object_inertia(np, self.obj.kind, self.obj.radius,
                                                                    self.obj.length, p["scale"], p["mass"])
        gain, bias = self.gainprm[ids], self.biasprm[ids]
        scale = p["torque_scale"][:, None] if "torque_scale" in p else 1.0  # N m per normalized torque unit
        task.set_gains(gain, bias, p["kp"] * scale, p["kd"] * scale)
        self.gainprm[ids], self.biasprm[ids] = gain, bias
        self._start_hardware_physics(ids, p)
        self.batch.set_const(ids)
        qpos = self.qpos[ids]
        qpos[:, : C.NUM_JOINTS] = q
        qpos[:, self.obj_qpos : self.obj_qpos + 7] = pose
        self.qpos[ids] = qpos
        self.qvel[ids] = 0.0
        self.ctrl[ids] = q
        xfrc = self.xfrc[ids]
        xfrc[:] = 0.0
        self.xfrc[ids] = xfrc
        self.batch.forward(ids)


def observation_space(cfg: EnvConfig) -> gym.spaces.Dict:
    """One env's observation groups, the same on both physics backends (touch and skin only when on)."""
    return gym.spaces.Dict(
        {
            "proprio": gym.spaces.Box(-np.inf, np.inf, (C.PROPRIO_STEPS, C.PROPRIO_DIM), np.float32),
            "proprio_hist": gym.spaces.Box(-np.inf, np.inf, (C.HISTORY_STEPS, C.PROPRIO_DIM), np.float32),
            "priv": gym.spaces.Box(-np.inf, np.inf, (C.PRIV_DIM,), np.float32),
            **({"tactile": tactile_space()} if cfg.tactile else {}),  # touch on
            **({"skin": skin_space()} if cfg.skin else {}),  # skin on
        }
    )


def action_space() -> gym.spaces.Box:
    """One env's actions: 16 joint-target deltas in [-1, 1] (scaled by the config's action_scale)."""
    return gym.spaces.Box(-1.0, 1.0, (C.NUM_JOINTS,), np.float32)


class RotateCupVec:
    """N RotateCup simulations stepped together; observations and rewards are (N, ...) numpy arrays."""

    render_mode: str | None = None
    """The core renders nothing itself; see envs.render for frames of any simulation."""

    def __init__(self, cfg: EnvConfig | None = None, num_envs: int = 1, seed: int = 0, nthread: int | None = None,
                 grasps: GraspCache | None = None):
        self.cfg = cfg = cfg if cfg is not None else EnvConfig()
        if not isinstance(cfg, EnvConfig):
            raise ValueError(f"cfg must be an EnvConfig, got {type(cfg).__name__}")
        if not isinstance(num_envs, numbers.Integral) or isinstance(num_envs, bool):
            raise ValueError(f"num_envs must be an integer, got {type(num_envs).__name__} {num_envs!r}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if nthread is not None:
            check_int("nthread", nthread, 1, 1024)
        seed = check_seed("seed", seed)
        self.num_envs = n = int(num_envs)
        # touch: the Digit 360 sensors exist only with tactile=True; the plain model is unchanged
        touch_sensors = partial(add_digit360_sensors, history=cfg.substeps) if cfg.tactile else None
        # skin: the Xela pad sensors exist only with skin=True (on the Xela hand)
        sensors = partial(add_xela_sensors, history=cfg.substeps) if cfg.skin else touch_sensors
        self.model, self.obj, self.max_scale = task_model(cfg, edit=sensors)
        m = self.model
        self.nthread = nthread if nthread is not None else max(1, min(os.cpu_count() or 1, n))
        self.batch = mujoco.batch.Batch(m, n, self.nthread, persistent=True)
        # touch: per-env contact history feeding obs["tactile"]; None keeps the plain path as it was
        self.touch = (TouchState(m, n, cfg.physics_dt, cfg.substeps,
                                 touch_model(cfg.hand)) if cfg.tactile else None)
        # skin: per-env Xela readings feeding obs["skin"] and the pad force labels; None when off
        self.skin = SkinState(m, n, cfg.physics_dt, cfg.substeps) if cfg.skin else None

        # episode starts (shared with the grasp hold check); the env keeps short names for its fields and views
        self.starts = st = EpisodeStarts(self.batch, m, self.obj, self.max_scale)
        self.obj_body, self.obj_geoms, self.obj_qpos = st.obj_body, st.obj_geoms, st.obj_qpos
        self._geom_size1, self._geom_pos1 = st.geom_size1, st.geom_pos1
        self._geom_size, self._geom_pos, self._geom_friction = st.geom_size, st.geom_pos, st.geom_friction
        self._body_mass, self._body_ipos, self._body_inertia = st.body_mass, st.body_ipos, st.body_inertia
        self._gainprm, self._biasprm = st.gainprm, st.biasprm
        self._qpos, self._qvel, self._ctrl, self._xfrc = st.qpos, st.qvel, st.ctrl, st.xfrc
        self._act_force = self.batch.bind("actuator_force")

        self.grasps = grasps if grasps is not None else load_default_cache(cfg.object, cfg.grasp_cache, cfg.hand)
        self.rng = CounterRNG(env_keys(seed, n))
        self.episode = np.full(n, -1, dtype=np.int64)  # the first reset starts episode 0, as reset(seed=seed) does
        self.steps = np.zeros(n, dtype=np.int64)
        self.targets = np.zeros((n, C.NUM_JOINTS))
        self.grasp_q = np.zeros((n, C.NUM_JOINTS))
        self.start_pos = np.zeros((n, 3))
        self.push = np.zeros((n, 3))
        self.params = {k: np.zeros(s) for k, s in
                       (("scale", n), ("mass", n), ("friction", n), ("com", (n, 3)), ("kp", (n, 16)), ("kd", (n, 16)))}
        self.hardware_physics = task.uses_hardware_physics(cfg)
        self.delay = np.zeros(n, dtype=np.int64)
        """Physics steps each env's new targets wait before they reach the motors (the action delay)."""
        self.history = ProprioHistory(n)
        self._axis = np.asarray(cfg.reward.axis, dtype=np.float64)
        self._needs_reset = True

        self.single_observation_space = observation_space(cfg)
        self.single_action_space = action_space()

    # ------------------------------------------------------------------ helpers
    def _nominal_scale(self) -> float:
        scales = self.cfg.randomization.scales
        return float(scales[len(scales) // 2])

    def _sample_params(self, ids: np.ndarray) -> dict[str, np.ndarray]:
        """Per-env physical parameters for envs ``ids`` (vectorized, keyed by env and episode; envs.task)."""
        zero = np.zeros(len(ids), np.int64)
        u = self.rng.uniform(ids, self.episode[ids], zero, _STREAM_RESET, task.PARAM_DRAWS)
        u_phys = (self.rng.uniform(ids, self.episode[ids], zero, _STREAM_PHYS, task.PHYS_DRAWS)
                  if self.hardware_physics else None)
        return task.sample_params(np, self.cfg, u, u_phys)

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, ids: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Reset envs ``ids`` (all by default); a seed (0 .. 2**64 - 1) re-keys every env (env i gets seed + i)."""
        if seed is not None:
            self.rng = CounterRNG(env_keys(check_seed("seed", seed), self.num_envs))
            self.episode[:] = -1
            ids = None
        ids = np.arange(self.num_envs) if ids is None else np.asarray(ids, dtype=np.int64)
        self._reset_ids(ids)
        self._needs_reset = False
        return self._observe()

    def _reset_ids(self, ids: np.ndarray) -> None:
        if len(ids) == 0:
            return
        self.episode[ids] += 1
        p = self._sample_params(ids)
        q, pose = self.grasps.sample(p["bucket"], p["scale"], p["grasp_u"])  # (k, 16), (k, 7)
        self.starts.start(ids, p, q, pose)
        for key in ("scale", "mass", "friction", "com", "kp", "kd"):
            self.params[key][ids] = p[key]
        for key in task.PHYS_KEYS:  # the hardware physics' draws, kept for reports (not in priv)
            if key in p:
                self.params.setdefault(key, np.zeros((self.num_envs, *np.shape(p[key])[1:])))[ids] = p[key]
        self.delay[ids] = p.get("delay", 0)
        self.targets[ids] = q
        self.grasp_q[ids] = q
        self.start_pos[ids] = pose[:, :3]
        self.steps[ids] = 0
        self.push[ids] = 0.0
        self.history.reset(ids, q)
        if self.touch is not None:  # touch: the reset reading fills the contact history
            self.touch.reset(ids, self.batch.bind("sensordata"), self.rng.keys[ids], self.episode[ids])
        if self.skin is not None:  # skin: the reset's load fills the window
            self.skin.reset(ids, self.batch.bind("sensordata"), self.rng.keys[ids], self.episode[ids])

    def _priv(self) -> np.ndarray:
        pos = self._qpos[:, self.obj_qpos : self.obj_qpos + 3]
        return task.priv_vector(np, pos, self.params).astype(np.float32)

    def _observe(self) -> dict[str, np.ndarray]:
        obs = {"proprio": self.history.proprio, "proprio_hist": self.history.history, "priv": self._priv()}
        if self.touch is not None:  # touch: windows rendered lazily on access (envs.sensors.tactile_obs)
            obs["tactile"] = self.touch.observe()
        if self.skin is not None:  # skin: the last WINDOW Xela samples (envs.sensors.skin_obs)
            obs["skin"] = self.skin.observe()
        return obs

    def step(self, actions: np.ndarray):
        """Advance every env one policy step. Returns (obs, reward, terminated, truncated, info)."""
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.num_envs, C.NUM_JOINTS):
            raise ValueError(f"actions must have shape ({self.num_envs}, {C.NUM_JOINTS}), got {a.shape}")
        if not np.all(np.isfinite(a)):
            bad = np.argwhere(~np.isfinite(a))[0]
            raise ValueError(f"actions must be finite; env {bad[0]} joint {bad[1]} is {a[tuple(bad)]}")
        cfg, rc, all_ids = self.cfg, self.cfg.randomization, np.arange(self.num_envs)
        self.targets = task.step_targets(np, cfg, self.targets, a, C.JOINT_LOWER, C.JOINT_UPPER)

        # random pushes on the object (Hora): new with probability p, otherwise decaying
        if rc.enabled and rc.push_prob > 0:
            new = self.rng.uniform(all_ids, self.episode, self.steps, _STREAM_PUSH_P, 1)[:, 0] < rc.push_prob
            normal = self.rng.normal(all_ids, self.episode, self.steps, _STREAM_PUSH_F, 3)
            self.push = task.step_push(np, cfg, self.push, new, normal, self.params["mass"])
            xfrc = self._xfrc
            xfrc[:, self.obj_body, :3] = self.push
            self._xfrc[:] = xfrc

        o = self.obj_qpos
        pos0 = self._qpos[:, o : o + 3].copy()
        quat0 = self._qpos[:, o + 3 : o + 7].copy()
        self._advance()
        if self.touch is not None:  # touch: every substep's sensor sample, from the sensors' history
            self.touch.push(self.batch.bind("history"))
        if self.skin is not None:  # skin: every substep is one 100 Hz sample
            self.skin.push(self.batch.bind("history"))
        qpos, qvel = self._qpos, self._qvel
        q, qdot = qpos[:, : C.NUM_JOINTS], qvel[:, : C.NUM_JOINTS]
        pos, quat = qpos[:, o : o + 3], qpos[:, o + 3 : o + 7]
        tau = self._act_force

        out = task.reward_and_termination(np, cfg, q=q, qdot=qdot, tau=tau, qpos=qpos, qvel=qvel, pos0=pos0,
                                          quat0=quat0, pos=pos, quat=quat, grasp_q=self.grasp_q,
                                          start_pos=self.start_pos, axis=self._axis)
        self.steps += 1
        terminated = out["fell"]
        truncated = (self.steps >= cfg.episode_steps) & ~terminated

        u = self.rng.uniform(all_ids, self.episode, self.steps, _STREAM_NOISE, 16)
        self.history.push(task.observed_joints(np, cfg, q, self.grasp_q, out["finite"], u), self.targets)
        info = task.step_info(np, cfg, out, pos, tau, self.steps)
        if self.skin is not None:  # skin: per-pad contact force label [normal, shear x, shear y] (N, pad frame)
            info["skin_force"] = self.skin.pad_force.copy()
        return self._observe(), out["reward"].astype(np.float64), terminated, truncated, info

    def _advance(self) -> None:
        """One control step of physics: each env's new targets reach its motors after its action delay (the old
        ones act until then)."""
        sub = self.cfg.substeps
        if not self.delay.any():
            self._ctrl[:] = self.targets
            self.batch.step(nstep=sub)
            return
        done = 0
        for d in np.unique(self.delay):  # the switch points, in order; delay < substeps
            if d > done:
                self.batch.step(nstep=int(d - done))
                done = int(d)
            ctrl, now = self._ctrl, self.delay == d
            ctrl[now] = self.targets[now]
            self._ctrl[:] = ctrl
        self.batch.step(nstep=sub - done)

    # ------------------------------------------------------------------ tools
    def get_data(self, i: int = 0) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """Model and data of simulation i, e.g. for rendering."""
        return self.batch.get_model(i), self.batch.get_data(i)

    def close(self) -> None:
        self.batch = None  # type: ignore[assignment]


def random_steps_per_s(env: RotateCupVec, steps: int, seed: int = 0) -> float:
    """Env transitions per second of ``env`` under uniform random actions, finished envs reset (benchmarks)."""
    iters = max(1, steps // env.num_envs)
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (iters, env.num_envs, C.NUM_JOINTS))
    env.reset()
    start = time.perf_counter()
    for t in range(iters):
        _, _, terminated, truncated, _ = env.step(actions[t])
        done = np.flatnonzero(terminated | truncated)
        if len(done):
            env.reset(ids=done)
    return iters * env.num_envs / (time.perf_counter() - start)
