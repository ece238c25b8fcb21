"""The MuJoCo model of the right Allegro hand with Digit 360 fingertips, generated from the vendor's figures.

    xml = hand_xml()                       # the MJCF text (palm up, no object)
    spec = mujoco.MjSpec.from_string(xml)

Every joint's origin, orientation and axis, the limits, the link and palm collision boxes and the masses come
from envs.allegro_description (the published figures, with their sources); the palm's frame is turned palm up
(envs.allegro_description.PALM_IN_WORLD) and sits at the world origin. The Digit 360 fingertips are a box for the
sensor body and a sphere for the dome, at Meta's mount offsets. Names follow envs.constants: joints
``<finger>_<0..3>``, actuators ``act_<joint>``, bodies ``<finger>_{base,proximal,medial,distal}``, the dome geom and
its site ``<finger>_tip`` (site z axis out of the dome, along the last link).

The defaults of the actuators and the contact parameters are those of the older model
(envs/assets/allegro_right_digit360.xml); the solver runs more iterations (SOLVER_ITERATIONS). The env's hand
variant 'digit360_v4' is this model (envs.scene), on the hardware's physics (envs.physics.V4_PHYSICS).
tests/envs/test_hand_model.py holds its kinematics to the vendor's figures.
"""

from __future__ import annotations

import mujoco
import numpy as np

from envs import allegro_description as D
from envs import constants as C

SEGMENTS = ("base", "proximal", "medial", "distal")
TIPS = ("digit360", "stock")
"""Fingertips the model can carry (hand_xml)."""
SOLVER_ITERATIONS = 50
SOLVER_LS_ITERATIONS = 20
"""Iterations of MuJoCo's Newton solver and of its line search. The older model's 20 / 8 are not enough here: its
box links and sensor housings give the cup more contacts, and under elliptic cones the solver stopped before it
converged, leaving forces that launched a held cup out of the hand (6 of 10 grasps without noslip, 1 with it, in
5 s held still); from 50 / 20 on the results no longer change (100 / 50 and 200 / 100 give the same sinks) and a
converged step costs no more wall time (experiments/sim_v4)."""
"""Body name suffixes of a finger's links, joint 0 to 3."""


def _f(values) -> str:
    return " ".join(f"{float(v):.6g}" for v in values)


def _quat(rpy: tuple[float, float, float]) -> str:
    """URDF rpy -> MuJoCo quaternion (w, x, y, z) text."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, D.rpy_matrix(rpy).reshape(-1))
    return _f(q)


def _finger_xml(finger: str, indent: str = "      ", tips: str = "digit360") -> str:
    """The nested bodies of one finger (or the thumb), joint 0 outward, with its fingertip: a Digit 360 (its body
    and dome) or the stock tip (``tips``)."""
    links = D.finger_links(finger)
    f = C.FINGERS.index(finger)
    lines: list[str] = []
    for k, link in enumerate(links):
        pad = indent + "  " * k
        j = 4 * f + k
        lines.append(f'{pad}<body name="{finger}_{SEGMENTS[k]}" pos="{_f(link.origin)}" quat="{_quat(link.rpy)}" '
                     'gravcomp="1">')
        lines.append(f'{pad}  <joint name="{link.joint}" axis="{_f(link.axis)}" '
                     f'range="{C.JOINT_LOWER[j]:.6g} {C.JOINT_UPPER[j]:.6g}"/>')
        half = np.asarray(link.box) / 2
        lines.append(f'{pad}  <geom name="{finger}_{SEGMENTS[k]}" type="box" size="{_f(half)}" '
                     f'pos="{_f(link.box_center)}" mass="{link.mass:.6g}"/>')
    pad = indent + "  " * (len(links) - 1)
    kind = "thumb" if finger == "thumb" else "finger"
    if tips == "digit360":
        mount = D.DIGIT360_MOUNT[kind]
        body = np.asarray(D.DIGIT360_BODY) / 2
        dome, radius = D.dome_offset(finger), D.DIGIT360_DOME_RADIUS
        lines.append(f'{pad}  <geom name="{finger}_digit360" class="tip_body" type="box" size="{_f(body)}" '
                     f'pos="0 0 {mount + body[2]:.6g}" mass="{D.DIGIT360_MASS:.6g}"/>')
        mass = ""
    else:  # the stock tip: a sphere on the last link, with the mass the vendor gives it
        dome, radius = D.STOCK_TIP_OFFSET[kind], D.STOCK_TIP_RADIUS
        mass = f' mass="{D.STOCK_TIP_MASS:.6g}"'
    lines.append(f'{pad}  <geom name="{finger}_tip" class="tip" type="sphere" size="{radius:.6g}" '
                 f'pos="0 0 {dome:.6g}"{mass}/>')
    lines.append(f'{pad}  <site name="{finger}_tip" pos="0 0 {dome:.6g}" zaxis="0 0 1" size="0.004" '
                 'rgba="1 0.3 0.3 1"/>')
    for k in reversed(range(len(links))):
        lines.append(indent + "  " * k + "</body>")
    return "\n".join(lines)


def hand_xml(tips: str = "digit360") -> str:
    """The MJCF text of the hand, palm up at the world origin, without an object; ``tips``: 'digit360' (Meta's
    Digit 360 fingertips) or 'stock' (the vendor's 12 mm tips, which the Xela hand's shells replace)."""
    if tips not in TIPS:
        raise ValueError(f"tips must be one of {', '.join(TIPS)}, got {tips!r}")
    fingers = "\n".join(_finger_xml(finger, tips=tips) for finger in C.FINGERS)
    half = np.asarray(D.PALM_BOX) / 2
    actuators = "\n".join(
        f'    <position name="{C.ACTUATOR_NAMES[j]}" class="allegro" joint="{name}" '
        f'ctrlrange="{C.JOINT_LOWER[j]:.6g} {C.JOINT_UPPER[j]:.6g}"/>' for j, name in enumerate(C.JOINT_NAMES))
    limit = C.DEFAULT_TORQUE_LIMIT
    excludes = "\n".join(f'    <exclude body1="palm" body2="{finger}_base"/>' for finger in C.FINGERS)
    name = "allegro_right_digit360_v4" if tips == "digit360" else "allegro_right_stock_v4"
    return f"""<mujoco model="{name}">
  <!-- Generated by envs.hand_model from the figures in envs.allegro_description (sources there). -->
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.01" integrator="implicitfast" cone="pyramidal" impratio="3" iterations="{SOLVER_ITERATIONS}"
          ls_iterations="{SOLVER_LS_ITERATIONS}">
    <flag eulerdamp="disable"/>
  </option>
  <default>
    <default class="allegro">
      <joint armature="0.001" frictionloss="0.01" damping="0.0"/>
      <position kp="{C.DEFAULT_KP:g}" kv="{C.DEFAULT_KD:g}" forcerange="{-limit:g} {limit:g}"/>
      <geom contype="1" conaffinity="2" condim="3" friction="1 0.01 0.001" solref="0.02 1" solimp="0.9 0.95 0.001"
            rgba="0.15 0.15 0.17 1"/>
      <default class="tip_body">
        <geom rgba="0.3 0.3 0.32 1"/>
      </default>
      <default class="tip">
        <geom condim="4" friction="1 0.01 0.001" rgba="0.85 0.85 0.8 1" mass="0"/>
      </default>
    </default>
  </default>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".25 .28 .32" rgb2=".2 .22 .25" width="256" height="256"/>
    <material name="floor" texture="grid" texrepeat="8 8" reflectance="0.1"/>
  </asset>
  <worldbody>
    <light name="key" pos="0.2 -0.3 0.6" dir="-0.3 0.5 -1" diffuse="0.8 0.8 0.8"/>
    <light name="fill" pos="-0.3 0.3 0.5" dir="0.5 -0.4 -1" diffuse="0.3 0.3 0.3"/>
    <geom name="floor" type="plane" size="0.5 0.5 0.01" pos="0 0 -0.25" material="floor" contype="0" conaffinity="0"/>
    <camera name="front" pos="0.30 -0.26 0.24" mode="targetbody" target="palm" fovy="40"/>
    <camera name="side" pos="0.02 -0.40 0.12" mode="targetbody" target="palm" fovy="40"/>
    <camera name="top" pos="0.03 0 0.45" xyaxes="0 1 0 -1 0 0" fovy="45"/>
    <body name="palm" childclass="allegro" quat="{_f(D.PALM_QUAT)}" gravcomp="1">
      <geom name="palm" type="box" size="{_f(half)}" pos="{_f(D.PALM_BOX_CENTER)}" mass="{D.PALM_MASS:g}"/>
{fingers}
    </body>
  </worldbody>
  <contact>
{excludes}
  </contact>
  <actuator>
{actuators}
  </actuator>
</mujoco>
"""


if __name__ == "__main__":
    print(hand_xml())
