"""The emulated hands' body: the project's MuJoCo hand (holding the cup) driven by joint torques.

Choice made here: the model's position actuators get zero gains (gain and bias), so ``ctrl`` does nothing, and
the torque commanded on the bus is written to ``qfrc_applied`` of the 16 hand DoFs (N m; the project uses
normalized torque = N m in simulation, envs/constants.py). The host's PD loop therefore closes through the
emulated bus exactly as on the real hand, with the bus delay included.

Thread-safe: one emulator thread advances it, others may read the joint state.
"""

from __future__ import annotations

import threading

import mujoco
import numpy as np

from envs.constants import HOME_POSE, JOINT_NAMES, NUM_JOINTS
from envs.objects import get_object
from envs.scene import OBJECT_JOINT, OBJECT_START, build_model

TIMESTEP = 1e-3
"""Physics step (s): 3 steps per 3 ms hand cycle; finer than the env's 10 ms because the torque loop is explicit."""


class HandPhysics:
    """MuJoCo hand + object; :meth:`advance` integrates with the last torque held constant (zero-order hold)."""

    def __init__(self, object_name: str = "cup", scale: float = 0.8, q0: np.ndarray | None = None) -> None:
        self.model = build_model(get_object(object_name), scale=scale, timestep=TIMESTEP)
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
        mujoco.mj_forward(self.model, self.data)
        self._torque = np.zeros(NUM_JOINTS)
        self._lock = threading.Lock()

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
        """Integrate ``seconds`` of hand time (rounded to whole physics steps)."""
        n = max(1, int(round(seconds / self.model.opt.timestep)))
        with self._lock:
            self.data.qfrc_applied[self._dof_adr] = self._torque
            for _ in range(n):
                mujoco.mj_step(self.model, self.data)
            if self.data.qpos[self._obj_qpos + 2] < -0.5:  # the object fell off: put it back above the hand
                self.data.qpos[self._obj_qpos: self._obj_qpos + 3] = OBJECT_START
                self.data.qpos[self._obj_qpos + 3: self._obj_qpos + 7] = (1.0, 0.0, 0.0, 0.0)
                self.data.qvel[self._obj_dof: self._obj_dof + 6] = 0.0

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(q rad, qdot rad/s), each (16,), bus order, Allegro frame."""
        with self._lock:
            return self.data.qpos[self._qpos_adr].copy(), self.data.qvel[self._dof_adr].copy()
