"""How the insertion task's hand holds the plug (envs.insertion): in its fingertips, or as it holds the cup; the
shaking task (envs.shake, ``grip='fingertips'``) stands its bottle in the same fingertip grip.

The benchmark this task rebuilds holds the plug in the fingertips, where the sensors carry the socket's forces. The
hand's grasps come from its cup grasp cache, whose grasps rest the cup on the phalanges (the domes carry about a
tenth of the load, experiments/insertion). The fingertip grip turns a cup grasp into a fingertip grasp:

- the plug's grip is a disc GRIP_HEIGHT tall (radius: the grasp's cup radius, at most GRIP_RADIUS) at the four domes'
  mean height, clear of the phalanges below;
- inverse kinematics (damped least squares on each finger's four joints) puts every dome's centre on the disc's
  wall at the dome's own azimuth, within the wall's height band: the start's joints;
- the joint targets command each dome SQUEEZE further towards the disc's axis, as a grasp controller squeezes
  (with the hand's position gain, 3 N m/rad, about 1-3 N per dome, a little more on the thumb that opposes the
  other three);
- not every grasp holds that way (the squeeze can press the disc out sideways where a dome lands low or a sensor's
  housing meets the disc first); :func:`holds` checks a settled grip, and the env takes the next grasp row
  (REGRIP_STEP further along the same bucket) until one holds, at most MAX_REGRIPS times.
"""

from __future__ import annotations

import mujoco
import numpy as np

from envs.constants import FINGERS
from envs.held_hand import Grip

GRIPS = ("fingertips", "palm")
"""How the plug is held: by the fingertips' domes, or as the cup is (its whole body on the phalanges; the first
version's runs)."""
FIRST_GRIP = "palm"
"""The grip of demonstrations and policies recorded before the grip was a setting."""
GRIP_HEIGHT = 0.03
"""Height (m) of the fingertip grip's disc: about a dome's diameter and a quarter, so that every dome meets its
side wall, and clear of the medial phalanges below."""
GRIP_RADIUS = 0.032
"""Largest radius (m) of the fingertip grip's disc (the cup grasp's radius where smaller)."""
SQUEEZE = 0.012
"""How far past the disc's wall (m) the joint targets command each dome, towards its axis. At 4 mm the domes
pressed 0.3-1 N and a 3 N push on the plug slid it out of 6 of 12 grasps; at 12 mm they press 1-3 N (the thumb up
to 6 N) and a 5 N push moves the plug 3-7 mm in 8 of 12."""
HOLD_DRIFT = 0.005
"""A settled grip holds when the plug moved at most this far (m, in the palm's frame) over the settling."""
MAX_REGRIPS = 8
"""Further grasp rows tried when one does not hold."""
REGRIP_STEP = 0.618034
"""Step of the grasp row (as a fraction of the bucket) between tries: the golden ratio's fractional part, so the
tries spread over the bucket."""


def check_grip(where: str, grip: str) -> None:
    if grip not in GRIPS:
        raise ValueError(f"{where}: grip must be one of {', '.join(GRIPS)}, got {grip!r}")


def fingertip_grip(spec: mujoco.MjSpec, g: Grip, height: float = GRIP_HEIGHT) -> tuple[Grip, np.ndarray, float]:
    """The fingertip grip at cup grasp ``g`` (module docstring), the wrist at its start. Returns the grip (the
    start's joints and the object's pose), the joint targets (16,) and the object's radius (m).

    ``height``: the held cylinder's height (m, at least GRIP_HEIGHT). A taller one (a bottle) stands on the same
    grip band: its lowest GRIP_HEIGHT is where the plug's disc would be, the rest above the fingertips."""
    if not height >= GRIP_HEIGHT:
        raise ValueError(f"fingertip grip: the object must be at least {GRIP_HEIGHT} m tall, got {height}")
    model = spec.compile()
    data = mujoco.MjData(model)
    adr = [[model.jnt_qposadr[model.joint(f"{f}_{j}").id] for j in range(4)] for f in FINGERS]
    dofs = [[model.jnt_dofadr[model.joint(f"{f}_{j}").id] for j in range(4)] for f in FINGERS]
    limits = [np.array([model.jnt_range[model.joint(f"{f}_{j}").id] for j in range(4)]) for f in FINGERS]
    domes = [model.geom(f"{f}_tip").id for f in FINGERS]
    data.qpos[np.ravel(adr)] = g.q
    mujoco.mj_kinematics(model, data)
    centre = np.concatenate([g.pose[:2], [float(np.mean([data.geom_xpos[i][2] for i in domes]))]])
    radius = min(g.radius, GRIP_RADIUS)
    reach = radius + float(model.geom_size[domes[0], 0])  # a dome's centre from the axis when it touches the wall
    band = GRIP_HEIGHT / 2 - 0.006  # a dome's centre stays this close to the wall's mid-height
    jac = np.zeros((3, model.nv))

    def solve(depth: float) -> np.ndarray:
        """Joints (16,) that put each dome's centre ``depth`` inside the wall."""
        q = np.array(g.q, dtype=float)
        for k, geom in enumerate(domes):
            data.qpos[np.ravel(adr)] = g.q
            mujoco.mj_kinematics(model, data)
            out = data.geom_xpos[geom][:2] - centre[:2]
            out /= max(float(np.linalg.norm(out)), 1e-9)
            z = float(np.clip(data.geom_xpos[geom][2], centre[2] - band, centre[2] + band))
            goal = np.concatenate([centre[:2] + (reach - depth) * out, [z]])
            for _ in range(8):  # damped least squares, the finger's joints kept in their limits
                mujoco.mj_kinematics(model, data)
                mujoco.mj_comPos(model, data)
                mujoco.mj_jac(model, data, jac, None, data.geom_xpos[geom], model.geom_bodyid[geom])
                j4 = jac[:, dofs[k]]
                step = j4.T @ np.linalg.solve(j4 @ j4.T + 1e-4 * np.eye(3), goal - data.geom_xpos[geom])
                data.qpos[adr[k]] = np.clip(data.qpos[adr[k]] + step, limits[k][:, 0], limits[k][:, 1])
            q[4 * k: 4 * k + 4] = data.qpos[adr[k]]
        return q

    axis = np.zeros(9)
    mujoco.mju_quat2Mat(axis, g.pose[3:])
    up = axis.reshape(3, 3)[:, 2] * (height - GRIP_HEIGHT) / 2  # a taller object's centre, up its own axis
    pose = np.concatenate([centre + up, g.pose[3:]])
    return Grip(solve(0.0), pose, g.scale), solve(SQUEEZE), radius


def holds(offsets: np.ndarray) -> bool:
    """Whether a settling's plug offsets (T, 3; palm frame, envs.held_hand.WristRun.run) stayed within HOLD_DRIFT."""
    offsets = np.asarray(offsets)
    return bool(np.all(np.isfinite(offsets)) and np.linalg.norm(offsets - offsets[0], axis=1).max() <= HOLD_DRIFT)


def regrip_row(u: float, attempt: int) -> float:
    """The grasp row (in [0, 1)) of try ``attempt`` (0: the drawn row ``u``)."""
    return float((u + attempt * REGRIP_STEP) % 1.0)
