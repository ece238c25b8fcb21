"""The emulated hands' body: the project's MuJoCo hand (holding the cup) driven by joint torques.

Choice made here: the model's position actuators get zero gains (gain and bias), so ``ctrl`` does nothing, and
the torque commanded on the bus is written to ``qfrc_applied`` of the 16 hand DoFs (N m; the project uses
normalized torque = N m in simulation, envs/constants.py). The host's PD loop therefore closes through the
emulated bus exactly as on the real hand, with the bus delay included.

Starting from an initial grasp (for ``rotate deploy --hand sim-*``): :meth:`HandPhysics.at_grasp` puts the hand's
joints and the object at one row of the shipped grasp cache at RotateCup-v0's nominal scale, the state an env
episode starts from, so a policy trained in the env can rotate the emulated cup. With ``hold=True`` the scene
stays frozen at that state until :meth:`HandPhysics.release` (the caller does it once the driver holds the hand):
the emulated hand has no torque until the driver's start-up sequence switches the motors on (over a Dynamixel
bus that is ~200 register round trips), and a cup left in an unpowered hand drops out of the grasp; the hold
stands in for the operator who keeps the cup in place until the hand holds it.

Touch: the model carries the env's Digit 360 sensors (envs.sensors.digit360, one sample kept), and
:meth:`HandPhysics.contact_fields` turns them into the env's contact-field rows, one per fingertip, with the env's
own readout (``Digit360Readout``): what the emulated Digit 360 sensors (rotation.sim_hardware.digit360_touch)
sample. Sensors do not change the dynamics. A held scene is still, so its accelerometers read gravity alone.

Thread-safe: one emulator thread advances it, others may read the joint state and the object pose.
"""

from __future__ import annotations

import threading
from functools import partial

import mujoco
import numpy as np

from envs.config import default_randomization
from envs.constants import DEFAULT_HAND, HOME_POSE, JOINT_NAMES, NUM_JOINTS
from envs.core import set_contact
from envs.grasp_cache import load_default_cache
from envs.objects import get_object
from envs.physics import hand_physics as physics_of
from envs.physics import object_friction
from envs.scene import OBJECT_JOINT, build_model, hand_variant, link_geoms, skin_geoms
from envs.sensors.digit360 import Digit360Readout, add_digit360_sensors, sensor_name
from envs.task import object_inertia

TIMESTEP = 1e-3
"""Physics step (s): 3 steps per 3 ms hand cycle; finer than the env's 10 ms because the torque loop is explicit."""


class HandPhysics:
    """MuJoCo hand + object; :meth:`advance` integrates with the last torque held constant (zero-order hold)."""

    def __init__(self, object_name: str = "cup", scale: float = 0.8, q0: np.ndarray | None = None,
                 object_pose: np.ndarray | None = None, hold: bool = False, hand: str = DEFAULT_HAND) -> None:
        """``q0``: initial joint angles (16,) rad, bus order (default: the vendor home pose); ``object_pose``:
        initial object position (3, m) + quaternion (4, wxyz), world frame (default: above the fingers, upright);
        ``hold``: keep the scene frozen until :meth:`release` (see the module docstring); ``hand``: the simulated
        hand variant (envs.scene.HANDS) with its contact model (envs.physics.HAND_PHYSICS) and, on a hand whose links
        have their own friction, the links' nominal coefficient; the other geoms keep the model's."""
        self.object_name = object_name
        self.hand = hand
        self.scale = float(scale)
        self.grasp: int | None = None
        """Grasp cache row the scene started from (set by :meth:`at_grasp`), None otherwise."""
        self.model = build_model(get_object(object_name), scale=scale, timestep=TIMESTEP,
                                 edit=partial(add_digit360_sensors, history=1), hand=hand)
        set_contact(self.model, physics_of(hand).contact)  # the hand's contact model
        link_friction = physics_of(hand).randomization.link_friction
        if link_friction is not None:  # links and palm with their own friction: the env's nominal (the range's
            # middle, envs.task.nominal_hardware_params), the object the smaller of its own and theirs (envs.core)
            obj = np.flatnonzero(self.model.geom_bodyid == self.model.body("object").id)
            nominal = float(np.mean(link_friction))
            self.model.geom_friction[link_geoms(self.model, obj), 0] = nominal
            self.model.geom_friction[obj, 0] = object_friction(self.model.geom_friction[obj, 0], nominal)
        self.model.actuator_gainprm[:, 0] = 0.0  # position actuators off: torque comes from qfrc_applied
        self.model.actuator_biasprm[:, :3] = 0.0
        self.data = mujoco.MjData(self.model)
        ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in JOINT_NAMES]
        self._qpos_adr = np.array([self.model.jnt_qposadr[i] for i in ids])
        self._dof_adr = np.array([self.model.jnt_dofadr[i] for i in ids])
        obj = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, OBJECT_JOINT)
        self._obj_qpos = int(self.model.jnt_qposadr[obj])
        self._obj_dof = int(self.model.jnt_dofadr[obj])
        self.data.qpos[self._qpos_adr] = HOME_POSE if q0 is None else q0
        if object_pose is not None:
            self.data.qpos[self._obj_qpos: self._obj_qpos + 7] = object_pose
        mujoco.mj_forward(self.model, self.data)
        self._torque = np.zeros(NUM_JOINTS)
        self._lock = threading.Lock()
        self._held = bool(hold)
        self._readout = Digit360Readout(self.model)
        self._steps = 0  # physics steps taken: the key of the contact-field cache
        self._fields: tuple[int, np.ndarray] | None = None  # (steps, (4, NUM_FIELDS)) of the last computation
        if self._held:
            self._still_sensors()

    def _still_sensors(self) -> None:
        """Recompute the acceleration-stage sensors as if the scene stood still (qacc = 0): a held scene reads
        gravity on its accelerometers, and its contact forces stay those of the forward pass."""
        self.data.qacc[:] = 0.0
        mujoco.mj_rnePostConstraint(self.model, self.data)  # body accelerations from qacc, for the accelerometers
        mujoco.mj_sensorAcc(self.model, self.data)

    @classmethod
    def at_grasp(cls, object_name: str = "cup", grasp: int = 0, hold: bool = True, hand: str = DEFAULT_HAND
                 ) -> HandPhysics:
        """The hand holding ``object_name`` as a RotateCup-v0 episode starts: row ``grasp`` of the shipped grasp
        cache (envs.grasps) in the bucket of the env's nominal scale (the middle randomization scale, as with
        randomization off), joints at the grasp pose, object at the grasp's pose. ValueError if no cache ships
        for the object or ``grasp`` is out of range."""
        cache = load_default_cache(object_name, hand=hand)
        scales = default_randomization(hand).scales
        scale = float(scales[len(scales) // 2])  # = envs.core.RotateCupVec._nominal_scale
        bucket = int(np.abs(cache.scales - scale).argmin())
        if not 0 <= grasp < cache.grasps.shape[1]:
            raise ValueError(f"grasp {grasp} out of range: the {object_name!r} cache has {cache.grasps.shape[1]} "
                             f"grasps per scale (0..{cache.grasps.shape[1] - 1})")
        row = cache.grasps[bucket, grasp]  # (23,) = q (16) + object position (3) + quaternion wxyz (4)
        physics = cls(object_name, float(cache.scales[bucket]), q0=row[:NUM_JOINTS], object_pose=row[NUM_JOINTS:],
                      hold=hold, hand=hand)
        physics.grasp = int(grasp)
        return physics

    def set_object(self, mass: float | None = None, friction: float | None = None,
                   com: tuple[float, float, float] | None = None) -> None:
        """Give the emulated object another mass (kg), sliding friction coefficient or center-of-mass offset (m,
        object frame), as the env's randomization writes them (envs.core: one coefficient for hand and object,
        except a hand whose links have their own, whose object then takes the smaller of the two; the inertia of a
        solid body of that mass). None keeps a value. Before the scene is released (a lab swapping objects)."""
        with self._lock:
            m, body = self.model, self.model.body("object").id
            if friction is not None:
                obj = np.flatnonzero(m.geom_bodyid == body)
                links = link_geoms(m, obj)
                link_friction = m.geom_friction[links, 0].copy()
                m.geom_friction[:, 0] = friction
                if default_randomization(self.hand).link_friction is not None and len(links):
                    m.geom_friction[links, 0] = link_friction
                    m.geom_friction[obj, 0] = object_friction(float(friction), float(link_friction.min()))
            if mass is not None:
                spec = get_object(self.object_name)
                m.body_mass[body] = mass
                m.body_inertia[body] = object_inertia(np, spec.kind, spec.radius, spec.length,
                                                      np.array([self.scale]), np.array([float(mass)]))[0]
            if com is not None:
                m.body_ipos[body] = com
            mujoco.mj_setConst(m, mujoco.MjData(m))  # at qpos0, in scratch data: the scene's state stays as it is
            mujoco.mj_forward(m, self.data)
            if self._held:
                self._still_sensors()

    def gravity_in_sensor(self, finger: str) -> np.ndarray:
        """(3,) gravity in g, (0, 0, -1) in the world, in the frame of fingertip ``finger``'s Digit 360 (its site's
        orientation at the last physics step): added to the accelerometer's specific force it gives the linear
        acceleration a sensor fusion reports."""
        adr = int(self.model.sensor(sensor_name(finger, "quat")).adr[0])
        with self._lock:
            q = self.data.sensordata[adr: adr + 4].copy()
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, q / np.linalg.norm(q))
        return rot.reshape(3, 3).T @ np.array([0.0, 0.0, -1.0])

    def object_properties(self) -> dict[str, float | list[float]]:
        """The emulated object's scale, mass (kg), sliding friction coefficient (of its contact with the
        fingertips: the larger of the object's and the skin's coefficients, as MuJoCo combines them; on a hand whose
        links have their own friction the object's geom holds the smaller of the two) and center-of-mass offset (m,
        object frame): what a lab would measure (rotation.data.properties)."""
        m, body = self.model, self.model.body("object").id
        friction = max(m.geom_friction[m.body_geomadr[body], 0], m.geom_friction[skin_geoms(m), 0].max())
        return {"scale": self.scale, "mass": float(m.body_mass[body]), "friction": float(friction),
                "com": [float(x) for x in m.body_ipos[body]]}

    @property
    def held(self) -> bool:
        """True while the scene is frozen at its initial state (``hold=True`` until :meth:`release`)."""
        return self._held

    def release(self) -> None:
        """End the initial hold: from now on :meth:`advance` integrates the physics."""
        with self._lock:
            self._held = False

    @property
    def time(self) -> float:
        """Emulated hand time (s)."""
        return float(self.data.time)

    def set_torque(self, torque: np.ndarray) -> None:
        """Joint torques (16,) N m, bus order, held until the next call."""
        with self._lock:
            self._torque[:] = torque

    def torque(self) -> np.ndarray:
        with self._lock:
            return self._torque.copy()

    def advance(self, seconds: float) -> None:
        """Integrate ``seconds`` of hand time (rounded to whole physics steps); nothing while :attr:`held`."""
        n = max(1, int(round(seconds / self.model.opt.timestep)))
        with self._lock:
            if self._held:  # frozen at the initial state until release() (module docstring)
                return
            self.data.qfrc_applied[self._dof_adr] = self._torque
            for _ in range(n):
                mujoco.mj_step(self.model, self.data)
            self._steps += n
            if self.data.qpos[self._obj_qpos + 2] < -0.5:  # the object fell off: put it back above the hand
                self.data.qpos[self._obj_qpos: self._obj_qpos + 3] = hand_variant(self.hand).object_start
                self.data.qpos[self._obj_qpos + 3: self._obj_qpos + 7] = (1.0, 0.0, 0.0, 0.0)
                self.data.qvel[self._obj_dof: self._obj_dof + 6] = 0.0

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(q rad, qdot rad/s), each (16,), bus order, Allegro frame."""
        with self._lock:
            return self.data.qpos[self._qpos_adr].copy(), self.data.qvel[self._dof_adr].copy()

    def object_pose(self) -> np.ndarray:
        """(7,) object position (m) + orientation quaternion (w, x, y, z), world frame."""
        with self._lock:
            return self.data.qpos[self._obj_qpos: self._obj_qpos + 7].copy()

    def contact_fields(self) -> np.ndarray:
        """(4, NUM_FIELDS) float32 Digit 360 contact fields of the fingertips (envs.sensors.digit360.FINGERS order,
        sensor frames, SI units), as the env computes them: the state at the start of the last physics step (the
        sensor stage of ``mj_step``), or the initial state before any step. Computed once per physics step."""
        with self._lock:
            if self._fields is None or self._fields[0] != self._steps:
                rows = self._readout.read_current(self.data.sensordata[None])[0, :, 0]  # (4, NUM_FIELDS)
                self._fields = (self._steps, rows)
            return self._fields[1].copy()
