"""Build the MuJoCo model of the hand holding one object.

The object is compiled at the largest scale the env may use; smaller per-simulation scales only shrink geom
sizes, so the compiled bounding volumes stay conservative and collision detection stays exact.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import mujoco
import numpy as np

from envs.objects import ObjectSpec

OBJECT_BODY = "object"
OBJECT_JOINT = "object_free"
OBJECT_START = np.array([0.05, -0.005, 0.07])
"""Nominal object centre above the fingers (m, world frame), where grasps are generated (the 'digit360' and 'xela'
hands)."""
HANDS = ("digit360", "xela", "digit360_v4")
"""Hand variants: 'digit360' (Digit 360 fingertips, the default, the model the shipped policies trained on), 'xela'
(stock-length fingertips with Xela shells, and Xela pads on the phalanges and palm: envs.sensors.xela_hand), and
'digit360_v4' (the vendor's published Allegro V4 kinematics with Meta's Digit 360 mount, envs.hand_model: the hand
the retrain of issue 72 moves to; no simulated touch yet)."""
OBJECT_STARTS = {"digit360": OBJECT_START, "xela": OBJECT_START, "digit360_v4": np.array([0.04, 0.0, 0.08])}
"""Where each hand's grasps are generated (m, world frame); the digit360_v4 hand holds the cup lower and closer to
the palm (experiments/hand_v4)."""


def object_start(hand: str = "digit360") -> np.ndarray:
    """The nominal object centre of a hand variant (OBJECT_STARTS)."""
    if hand not in OBJECT_STARTS:
        raise ValueError(f"unknown hand {hand!r}; hands: {', '.join(HANDS)}")
    return OBJECT_STARTS[hand]


def hand_xml_path() -> str:
    return str(Path(__file__).resolve().parent / "assets" / "allegro_right_digit360.xml")


def hand_spec(hand: str = "digit360") -> mujoco.MjSpec:
    """The spec of a hand variant (one of HANDS), without an object."""
    if hand not in HANDS:
        raise ValueError(f"unknown hand {hand!r}; hands: {', '.join(HANDS)}")
    if hand == "digit360_v4":
        from envs.hand_model import hand_xml

        return mujoco.MjSpec.from_string(hand_xml())
    spec = mujoco.MjSpec.from_file(hand_xml_path())
    if hand == "xela":
        from envs.sensors.xela_hand import make_xela_hand

        make_xela_hand(spec)
    return spec


def build_model(obj: ObjectSpec, scale: float = 1.0, timestep: float = 0.01,
                edit: Callable[[mujoco.MjSpec], None] | None = None, hand: str = "digit360") -> mujoco.MjModel:
    """Compile the hand + object model with the object at ``scale`` (the env's largest).

    ``edit`` may add elements to the finished spec before compiling (e.g. the Digit 360 sensors); ``hand`` picks
    the hand variant (HANDS).
    """
    spec = hand_spec(hand)
    spec.option.timestep = timestep
    body = spec.worldbody.add_body(name=OBJECT_BODY, pos=object_start(hand).tolist())
    body.add_freejoint(name=OBJECT_JOINT)
    for i, g in enumerate(obj.geoms(scale)):
        body.add_geom(
            name=f"object_{i}", type=g["type"], size=list(g["size"]), pos=list(g["pos"]), quat=list(g["quat"]),
            contype=2, conaffinity=1, condim=4, friction=[1.0, 0.01, 0.001], density=400.0,
            solref=[0.02, 1.0], solimp=[0.9, 0.95, 0.001, 0.5, 2.0], rgba=[0.85, 0.45, 0.2, 1.0],
        )
    body.add_site(name="object_center", pos=[0, 0, 0], size=[0.004, 0, 0], rgba=[0, 0, 1, 1])
    if edit is not None:
        edit(spec)
    return spec.compile()
