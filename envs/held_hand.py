"""A hand on a moving wrist holding an object at one of its cup grasps: the scene the touch benchmarks share (bottle
shaking, envs.shake; object-action-surface, envs.oas).

The hand variant's model (envs.scene) gets its palm on a free joint welded to a mocap body, ``wrist_target``: a stiff
spring (WELD_TIMECONST, WELD_SOLIMP) that follows a scripted motion as a robot arm's wrist would. The held object stands
where the grasp puts the cup (the hand's cup grasp cache: the grasp's joints and the cup's pose at its scale); it
collides with the hand as the rotation env's objects do. :func:`finish` compiles the scene with the four Digit 360
sensors (or, on a Xela hand, the skin's pad sensors: envs.held_skin), the hand's contact model and vendor torque limits,
and the middle of the hand's friction ranges (tips, links; the object at the smaller of the two, so that each contact
takes the hand's side), as the rotation env's nominal physics (envs.physics).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import mujoco
import numpy as np

from envs.constants import FINGERS
from envs.grasp_cache import GraspCache
from envs.physics import hand_physics
from envs.scene import hand_spec, link_geoms, skin_geoms
from envs.sensors.digit360 import NUM_FIELDS, Digit360Readout, add_digit360_sensors, sensor_name
from envs.sensors.xela_hand import add_xela_sensors
from envs.sensors.xela_layout import XELA_HANDS

WELD_TIMECONST = 0.005
"""Time constant (s) of the weld that makes the palm follow the wrist's mocap body (at least two 2 ms steps)."""
WELD_SOLIMP = (0.99, 0.999, 0.001)
"""Its impedance: with MuJoCo's default (0.9, 0.95) and 10 ms the 0.95 kg hand sagged 17.7 mm below the wrist;
with these, 0.5 mm."""
OBJECT_CONTYPE = 2
"""The held object's collision type: the hand's geoms (contype 1, conaffinity 2) collide with it."""
CUP_RADIUS, CUP_HEIGHT = 0.040, 0.085
"""The cup's body at scale 1 (envs.objects 'cup'): a held object has its outer size at the grasp's scale."""


@dataclass(frozen=True)
class Grip:
    """Where a grasp holds the object: joint targets (16,), the object's pose (7,) and its size."""

    q: np.ndarray
    pose: np.ndarray
    scale: float

    @property
    def radius(self) -> float:
        return CUP_RADIUS * self.scale

    @property
    def height(self) -> float:
        return CUP_HEIGHT * self.scale


def check_touch_hand(task: str, hand: str, skin: bool = False) -> None:
    """ValueError unless ``hand`` has Digit 360 fingertips (the touch benchmarks' and insertion's sensors), or,
    where the task allows the skin (``skin``), is the vendor-kinematics Xela hand."""
    if hand in ("digit360", "digit360_v4") or (skin and hand == "xela_v4"):
        return
    allowed = "'digit360' or 'digit360_v4'" + (", or the Xela skin on 'xela_v4'" if skin else "")
    raise ValueError(f"{task}: the hand must have Digit 360 fingertips ({allowed}), got {hand!r}")


def contact_press(m: mujoco.MjModel, d: mujoco.MjData, body: int, wrench: np.ndarray,
                  force: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """Sum of the normal forces (N) of the contacts that involve ``body``'s geoms, and the force-weighted sum of their
    positions (N m, world frame; divided by the force, where the press is centred). ``force`` (3,), where given,
    gathers in the same pass the world-frame force (N) those contacts exert on ``body``, normal and friction."""
    total, moment = 0.0, np.zeros(3)
    for i in range(d.ncon):
        con = d.contact[i]
        b1, b2 = m.geom_bodyid[con.geom1], m.geom_bodyid[con.geom2]
        if b1 == body or b2 == body:
            mujoco.mj_contactForce(m, d, i, wrench)
            total += wrench[0]
            moment += wrench[0] * con.pos
            if force is not None:  # the contact's force on geom2, whose side its normal points to
                world = con.frame.reshape(3, 3).T @ wrench[:3]
                force += world if b2 == body else -world
    return total, moment


def contact_force(m: mujoco.MjModel, d: mujoco.MjData, body: int, wrench: np.ndarray) -> float:
    """Sum of the normal forces (N) of the contacts that involve ``body``'s geoms."""
    return contact_press(m, d, body, wrench)[0]


def contact_force_on(m: mujoco.MjModel, d: mujoco.MjData, body: int, wrench: np.ndarray) -> np.ndarray:
    """The world-frame force (N, (3,)) that the contacts involving ``body``'s geoms exert on it, normal and friction
    together. On the insertion socket (whose only contacts are the prong's), its negative is the external force on
    the hand and plug: what a force sensor between the arm and the hand measures, the hand's weight compensated."""
    force = np.zeros(3)
    contact_press(m, d, body, wrench, force)
    return force


def grip(grasps: GraspCache, bucket: int, u: float) -> Grip:
    """Row ``u`` (in [0, 1)) of grasp bucket ``bucket``."""
    scale = float(grasps.scales[bucket])
    q, pose = grasps.sample(np.array([bucket]), np.array([scale]), np.array([u]))
    return Grip(q[0], pose[0], scale)


def wrist_spec(hand: str, timestep: float) -> tuple[mujoco.MjSpec, np.ndarray]:
    """The hand's spec with its palm welded to the mocap body ``wrist_target``; returns it and the palm's start
    quaternion."""
    spec = hand_spec(hand)
    spec.option.timestep = timestep
    palm = spec.body("palm")
    palm.add_freejoint(name="wrist")
    spec.worldbody.add_body(name="wrist_target", mocap=True, pos=list(palm.pos), quat=list(palm.quat))
    weld = spec.add_equality(type=mujoco.mjtEq.mjEQ_WELD, name1="palm", name2="wrist_target",
                             objtype=mujoco.mjtObj.mjOBJ_BODY)
    weld.solref = [WELD_TIMECONST, 1.0]
    weld.solimp = [*WELD_SOLIMP, 0.5, 2.0]
    return spec, np.array(palm.quat, dtype=float)


def _middle(lo: float, hi: float, log: bool) -> float:
    return math.sqrt(lo * hi) if log else (lo + hi) / 2


def finish(spec: mujoco.MjSpec, hand: str, object_prefix: str, noslip: bool = True) -> mujoco.MjModel:
    """Compile the scene (see the module docstring); geoms named ``object_prefix``* are the held object's.
    ``noslip=False`` leaves MuJoCo's noslip solver out of the hand's contact model."""
    from envs.config import EnvConfig
    from envs.core import set_contact, set_torque_limits

    if hand in XELA_HANDS:
        add_xela_sensors(spec, history=1)
    else:
        add_digit360_sensors(spec, history=1)
    m = spec.compile()
    contact = hand_physics(hand).contact
    set_contact(m, contact if noslip else dataclasses.replace(contact, noslip_iterations=0))
    set_torque_limits(m, EnvConfig(hand=hand))
    rc = hand_physics(hand).randomization
    tip = _middle(*rc.friction, rc.friction_log)
    link = _middle(*rc.link_friction, False) if rc.link_friction is not None else tip
    held = np.array([g for g in range(m.ngeom) if m.geom(g).name.startswith(object_prefix)])
    m.geom_friction[link_geoms(m, held), 0] = link
    m.geom_friction[skin_geoms(m), 0] = tip
    m.geom_friction[held, 0] = min(tip, link)
    return m


class WristRun:
    """Steps a compiled held-hand scene with a scripted wrist and records the fingertips' contact fields."""

    def __init__(self, model: mujoco.MjModel, grip_: Grip, palm_quat: np.ndarray, held_body: str,
                 targets: np.ndarray | None = None) -> None:
        self.model, self.grip, self.palm_quat = model, grip_, palm_quat
        self.targets = grip_.q if targets is None else np.asarray(targets, dtype=float)
        """The joints' position targets (16,): the grasp's joints, or past them where the grip squeezes."""
        self.data = mujoco.MjData(model)
        digit360 = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, sensor_name(FINGERS[0], "contact")) >= 0
        self.readout = Digit360Readout(model) if digit360 else None
        """The fingertips' contact fields; None on a Xela hand (its skin: envs.held_skin.SkinHistory)."""
        from envs import constants as C

        self._joints = np.array([model.jnt_qposadr[model.joint(name).id] for name in C.JOINT_NAMES])
        self._palm, self._held = model.body("palm").id, model.body(held_body).id

    def reset(self, pos: np.ndarray, quat: np.ndarray) -> None:
        """The start: the grasp's joints and the targets, the wrist's mocap at (pos, quat), everything at rest."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[self._joints] = self.grip.q
        d.ctrl[:] = self.targets
        d.mocap_pos[0], d.mocap_quat[0] = pos, quat
        mujoco.mj_forward(m, d)

    def run(self, steps: int, wrist, on_step=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``steps`` physics steps, the wrist at ``wrist(t) -> (pos, quat)`` before each; ``on_step(data)`` after
        each. Returns the times (T,), contact fields (4, T, NUM_FIELDS; (4, T, 0) on a Xela hand) and the held
        object's centre relative to the palm in the palm's frame (T, 3)."""
        m, d = self.model, self.data
        times = np.empty(steps)
        rows = np.empty((4, steps, NUM_FIELDS if self.readout is not None else 0), np.float32)
        offset = np.empty((steps, 3))
        rot = np.zeros(9)
        for k in range(steps):
            d.mocap_pos[0], d.mocap_quat[0] = wrist(d.time)
            times[k] = d.time
            mujoco.mj_step(m, d)
            if self.readout is not None:
                rows[:, k] = self.readout.read_current(d.sensordata[None])[0, :, 0]
            mujoco.mju_quat2Mat(rot, d.xquat[self._palm])
            offset[k] = rot.reshape(3, 3).T @ (d.xpos[self._held] - d.xpos[self._palm])
            if on_step is not None:
                on_step(d)
        if not np.all(np.isfinite(rows)):
            raise FloatingPointError("the simulation diverged (non-finite contact fields)")
        return times, rows, offset


def tilt_quat(base: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``base`` turned by ``angle`` (rad) about the world ``axis`` (unit)."""
    turn = np.array([math.cos(angle / 2), *(math.sin(angle / 2) * np.asarray(axis, dtype=float))])
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, turn, base)
    return out


class TouchHistory:
    """The fingertips' recent contact fields, rendered on request into the Digit 360 windows a policy reads: the
    same windows the session loader renders from a recorded session with the same noise ``key``
    (rotation.data.dataset.session_key), so a closed-loop policy meets the touch it was trained on."""

    KEEP_S = 1.5
    """History kept (s): a window needs 1.12 s of it."""

    def __init__(self, key: int, dt: float, hand: str) -> None:
        from envs.scene import touch_model

        self.key, self.dt, self.model = int(key), float(dt), touch_model(hand)
        self.times = np.zeros(0)
        self.rows = np.zeros((4, 0, NUM_FIELDS), np.float32)

    def extend(self, times: np.ndarray, rows: np.ndarray) -> None:
        """Append the contact fields (4, S, NUM_FIELDS) of times (S,)."""
        self.times = np.concatenate([self.times, np.asarray(times, dtype=np.float64)])
        self.rows = np.concatenate([self.rows, np.asarray(rows, dtype=np.float32)], axis=1)
        keep = self.times >= self.times[-1] - self.KEEP_S
        self.times, self.rows = self.times[keep], self.rows[:, keep]

    def windows(self, fingers: tuple[str, ...] | None = None) -> dict[str, dict[str, np.ndarray]]:
        """{finger: raw window} ending at the newest 30 fps frame the history covers (envs.sensors.digit360_render:
        ``image`` (2, 224, 224, 3) uint8, ``audio`` (2, 27000), ``imu`` (224, 3), ``pressure`` (224,)); a
        ValueError when the history is shorter than a window."""
        from envs import constants as C
        from envs.sensors.digit360_model import IMAGE_HZ, ContactTrack, finger_key
        from envs.sensors.digit360_render import WindowIndex, render_window

        if not len(self.times):
            raise ValueError("TouchHistory: no contact fields yet")
        frame = int(math.floor(self.times[-1] * IMAGE_HZ + 1e-6))
        if WindowIndex(frame).start_time < self.times[0] - 1e-6:
            raise ValueError(f"TouchHistory: {self.times[-1] - self.times[0]:.2f} s of history, a window needs 1.12 s")
        out = {}
        for finger in fingers or C.FINGERS:
            f = C.FINGERS.index(finger)
            track = ContactTrack(self.times, self.rows[f], self.dt)
            out[finger] = render_window(track, frame, int(finger_key(self.key, f)), f, self.model)
        return out
