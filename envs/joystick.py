"""The joystick fixture (Sparsh-skin's joystick task): the Xela hand presses and pushes a spring-returned stick.

A stick hangs from a pivot above the palm on a 3-DoF ball joint with a torsional spring (``JoystickConfig.spring``)
that returns it to vertical, and a knob at its lower end where the hand's fingers close. :class:`JoystickPlay` runs
N such simulations (``mujoco.batch.Batch``, one per env) with the Xela skin on, driven by scripted motions of the
hand (``motion``): 'play' closes and opens the grip in cycles while sweeping the fingers and the thumb with slow
sines, so the knob is grasped, pushed around, twisted and let go (the spring brings the stick back); 'random' moves
the joint targets by low-pass filtered noise around the same grasp. Every 100 Hz skin sample comes with the stick's
roll, pitch and yaw (rad): the intrinsic z-y-x (yaw, pitch, roll) angles of the stick's rotation from rest, from a
``ballquat`` sensor, so roll tilts the knob toward +-y, pitch toward -+x, and yaw twists it about the stick.

Motions are deterministic under (env key, episode), like the RotateCup core (envs.rng).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Literal

import mujoco
import mujoco.batch
import numpy as np

from envs import constants as C
from envs.grasps import FLEX_JOINTS
from envs.rng import env_keys
from envs.scene import CANONICAL_POSE, hand_spec
from envs.sensors.skin_obs import SkinState
from envs.sensors.xela import SAMPLE_HZ
from envs.sensors.xela_hand import add_xela_sensors, read_ring
from envs.validation import check_int, check_number, check_seed, check_types

JOINT = "joystick_ball"
PIVOT = (0.045, -0.01, 0.155)
"""Pivot of the ball joint (m, world = hand frame), above the point where the canonical grasp closes."""
STICK_LENGTH = 0.08
"""Pivot to knob centre (m)."""
KNOB_RADIUS = 0.022
"""Knob radius (m): a vertical capsule the fingers and thumb close on."""
KNOB_HALF = 0.012
"""Half length of the knob capsule's straight part (m)."""


@dataclass(frozen=True)
class JoystickConfig:
    """The fixture and the hand's motions."""

    motion: Literal["play", "random"] = "play"
    """'play': scripted grip cycles and finger sweeps; 'random': filtered random joint targets around the grasp."""
    spring: float = 0.2
    """Stiffness of the return spring (N m / rad), the same for tilt and twist."""
    damping: float = 0.01
    """Damping of the ball joint (N m s / rad)."""
    max_tilt: float = 0.7
    """Range of the ball joint (rad): the stick stops at this angle from vertical."""
    control_hz: float = C.CONTROL_HZ
    """Rate of the hand's joint targets (Hz)."""
    kp: float = C.DEFAULT_KP
    """Joint proportional gain (N m / rad)."""
    kd: float = C.DEFAULT_KD
    """Joint damping gain (N m s / rad)."""

    def __post_init__(self) -> None:
        check_types(self)
        check_number("spring", self.spring, 0.0, 10.0, low_open=True, unit="N m / rad")
        check_number("damping", self.damping, 0.0, 1.0, unit="N m s / rad")
        check_number("max_tilt", self.max_tilt, 0.0, 1.5, low_open=True, unit="rad")
        check_number("control_hz", self.control_hz, 1.0, SAMPLE_HZ, unit="Hz")  # at most one target per step
        check_number("kp", self.kp, 0.0, 100.0, low_open=True, unit="N m / rad")
        check_number("kd", self.kd, 0.0, 10.0, unit="N m s / rad")
        sub = 1.0 / (self.control_hz * self.physics_dt)
        if abs(sub - round(sub)) > 1e-6:
            raise ValueError(f"control_hz: 100 Hz / control_hz must be a whole number of physics steps, got {sub:.4f}")

    @property
    def physics_dt(self) -> float:
        """Physics step (s): one skin sample per step (100 Hz)."""
        return 1.0 / SAMPLE_HZ

    @property
    def substeps(self) -> int:
        return round(1.0 / (self.control_hz * self.physics_dt))

    @property
    def control_dt(self) -> float:
        return 1.0 / self.control_hz


def add_joystick(spec: mujoco.MjSpec, cfg: JoystickConfig) -> None:
    """Add the fixture (a stick on a sprung ball joint at PIVOT) to a hand spec."""
    base = spec.worldbody.add_body(name="joystick_base", pos=list(PIVOT))
    base.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.01, 0, 0], contype=0, conaffinity=0,
                  rgba=[0.3, 0.3, 0.3, 1.0])
    stick = base.add_body(name="joystick_stick")
    stick.add_joint(name=JOINT, type=mujoco.mjtJoint.mjJNT_BALL, stiffness=cfg.spring, damping=cfg.damping,
                    range=[0.0, cfg.max_tilt], limited=mujoco.mjtLimited.mjLIMITED_TRUE, armature=1e-4)
    common = dict(contype=2, conaffinity=1, condim=4, friction=[1.0, 0.01, 0.001], solref=[0.02, 1.0],
                  solimp=[0.9, 0.95, 0.001, 0.5, 2.0], density=300.0)
    stick.add_geom(name="joystick_shaft", type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.006, 0, 0],
                   fromto=[0, 0, 0, 0, 0, -(STICK_LENGTH - KNOB_HALF)], rgba=[0.2, 0.2, 0.22, 1.0], **common)
    stick.add_geom(name="joystick_knob", type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[KNOB_RADIUS, KNOB_HALF, 0],
                   pos=[0, 0, -STICK_LENGTH], rgba=[0.85, 0.25, 0.2, 1.0], **common)
    sensor = spec.add_sensor(name="joystick_quat", type=mujoco.mjtSensor.mjSENS_BALLQUAT,
                             objtype=mujoco.mjtObj.mjOBJ_JOINT, objname=JOINT)
    sensor.nsample = cfg.substeps


def joystick_angles(quat: np.ndarray) -> np.ndarray:
    """(..., 4) stick rotations (w, x, y, z) -> (..., 3) [roll, pitch, yaw] rad (intrinsic z-y-x)."""
    w, x, y, z = np.moveaxis(quat / np.linalg.norm(quat, axis=-1, keepdims=True), -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


OPEN_POSE = np.clip(CANONICAL_POSE - np.isin(np.arange(16), FLEX_JOINTS) * 0.45, C.JOINT_LOWER, C.JOINT_UPPER)
"""Where every episode starts: the canonical grasp opened by 0.45 rad per flexion joint (clear of the knob)."""
_ABDUCTION = np.array([0, 4, 8, 12])


class JoystickPlay:
    """N simulations of the Xela hand playing with the joystick; one :meth:`step` is one control step."""

    def __init__(self, cfg: JoystickConfig | None = None, num_envs: int = 1, seed: int = 0,
                 nthread: int | None = None):
        self.cfg = cfg = cfg if cfg is not None else JoystickConfig()
        if not isinstance(cfg, JoystickConfig):
            raise ValueError(f"cfg must be a JoystickConfig, got {type(cfg).__name__}")
        check_int("num_envs", num_envs, 1, 4096)
        self.num_envs = n = int(num_envs)
        seed = check_seed("seed", seed)
        spec = hand_spec("xela")
        spec.option.timestep = cfg.physics_dt
        add_joystick(spec, cfg)
        add_xela_sensors(spec, cfg.substeps)
        self.model = m = spec.compile()
        m.actuator_gainprm[:, 0] = cfg.kp
        m.actuator_biasprm[:, 1] = -cfg.kp
        m.actuator_biasprm[:, 2] = -cfg.kd
        self.batch = mujoco.batch.Batch(m, n, nthread or max(1, min(os.cpu_count() or 1, n)), persistent=True)
        self.skin = SkinState(m, n, cfg.physics_dt, cfg.substeps)
        sid = m.sensor("joystick_quat").id
        self._quat_hist = (np.array([m.sensor_historyadr[sid]]), int(m.sensor_history[sid, 0]), 4)
        self._quat_adr = int(m.sensor_adr[sid])
        self._ball = int(m.joint(JOINT).qposadr[0])
        self.keys = env_keys(seed, n)
        self.episode = np.full(n, -1, dtype=np.int64)
        self.steps = np.zeros(n, dtype=np.int64)
        self.targets = np.tile(OPEN_POSE, (n, 1))
        self.last_angles = np.zeros((n, cfg.substeps, 3))
        """(N, S, 3) roll, pitch, yaw (rad) at the last step's skin samples."""
        self._motion = np.zeros((n, 5, 16))  # per env: amplitude, frequency (Hz), phase, grip period (s), grip phase
        self._filtered = np.zeros((n, 16))
        self._rngs: list[np.random.Generator | None] = [None] * n

    @property
    def angles(self) -> np.ndarray:
        """(N, 3) roll, pitch, yaw (rad) now."""
        return self.last_angles[:, -1]

    def reset(self, ids: np.ndarray | None = None) -> None:
        """Start envs ``ids`` (all by default) on their next episode: hand open at OPEN_POSE, stick at rest."""
        ids = np.arange(self.num_envs) if ids is None else np.asarray(ids, dtype=np.int64)
        self.episode[ids] += 1
        self.batch.reset(ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        qpos, ctrl = self.batch.bind("qpos"), self.batch.bind("ctrl")
        q = qpos[ids]
        q[:, :16] = OPEN_POSE
        q[:, self._ball : self._ball + 4] = [1.0, 0.0, 0.0, 0.0]
        qpos[ids] = q
        self.batch.bind("qvel")[ids] = 0.0
        ctrl[ids] = OPEN_POSE
        self.batch.forward(ids)
        for i in ids:
            rng = np.random.default_rng([int(self.keys[i]), int(self.episode[i])])
            self._rngs[i] = rng
            motion = np.zeros((5, 16))
            motion[0] = rng.uniform(0.05, 0.25, 16)  # sweep amplitude (rad)
            motion[0, _ABDUCTION] = rng.uniform(0.1, 0.3, 4)
            motion[1] = rng.uniform(0.15, 0.8, 16)  # sweep frequency (Hz)
            motion[2] = rng.uniform(0, 2 * math.pi, 16)
            motion[3] = rng.uniform(1.5, 4.0)  # grip cycle period (s)
            motion[4] = rng.uniform(0, 2 * math.pi)
            self._motion[i] = motion
        self._filtered[ids] = 0.0
        self.targets[ids] = OPEN_POSE
        self.steps[ids] = 0
        sensordata = self.batch.bind("sensordata")
        self.skin.reset(ids, sensordata, self.keys[ids], self.episode[ids])
        quat = sensordata[ids][:, self._quat_adr : self._quat_adr + 4]
        self.last_angles[ids] = joystick_angles(quat)[:, None]

    def _targets(self) -> np.ndarray:
        """Joint targets of every env for the next control step."""
        t = (self.steps + 1) * self.cfg.control_dt  # (N,)
        mo = self._motion
        flex = np.isin(np.arange(16), FLEX_JOINTS)
        # grip: 0 = open (OPEN_POSE), 1 = closed past the canonical grasp (squeezing the knob)
        grip = 0.5 - 0.5 * np.cos(2 * math.pi * t / mo[:, 3, 0] + mo[:, 4, 0])
        grip = np.clip(1.6 * grip - 0.2, 0.0, 1.0)[:, None]  # hold fully open and fully closed for a while
        base = OPEN_POSE + grip * flex * 0.6
        if self.cfg.motion == "play":
            sweep = mo[:, 0] * np.sin(2 * math.pi * mo[:, 1] * t[:, None] + mo[:, 2])
        else:
            u = np.stack([r.uniform(-1.0, 1.0, 16) for r in self._rngs])
            self._filtered = 0.85 * self._filtered + 0.15 * u
            sweep = self._filtered * 3.0 * mo[:, 0]
        return np.clip(base + sweep, C.JOINT_LOWER, C.JOINT_UPPER)

    def step(self) -> None:
        """One control step of every env: new targets, ``substeps`` physics steps, skin and stick readings."""
        self.targets = self._targets()
        self.batch.bind("ctrl")[:] = self.targets
        self.batch.step(nstep=self.cfg.substeps)
        history = self.batch.bind("history")
        self.skin.push(history)
        _, quat = read_ring(history, *self._quat_hist, self.cfg.substeps)  # (N, 1, S, 4)
        self.last_angles = joystick_angles(quat[:, 0])
        self.steps += 1

    def joints(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 16) joint positions (rad) and actuator torques (N m) now."""
        return self.batch.bind("qpos")[:, :16].copy(), self.batch.bind("actuator_force").copy()

    def get_data(self, i: int = 0) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """Model and data of simulation i, e.g. for rendering."""
        return self.batch.get_model(i), self.batch.get_data(i)

    def close(self) -> None:
        self.batch = None  # type: ignore[assignment]
