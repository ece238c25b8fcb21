"""Build the MuJoCo model of the hand holding one object.

The object is compiled at the largest scale the env may use; smaller per-simulation scales only shrink geom
sizes, so the compiled bounding volumes stay conservative and collision detection stays exact.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from envs.constants import DEFAULT_HAND, FINGERS
from envs.objects import ObjectSpec
from envs.sensors.digit360_model import Digit360Model

OBJECT_BODY = "object"
OBJECT_JOINT = "object_free"
OBJECT_START = np.array([0.05, -0.005, 0.07])
"""Nominal object centre above the fingers (m, world frame) of the 'digit360' and 'xela' hands."""
CANONICAL_POSE = np.array(
    [0.05, 0.34, 0.60, 0.89, -0.03, 0.42, 0.38, 0.80, -0.19, 0.70, -0.07, 1.04, 1.34, 0.02, 0.35, 1.17]
)
"""Pose of the 'digit360' and 'xela' hands putting three fingertips on the +x side and the thumb on the -x side of
an object at OBJECT_START (found by a sampling IK on fingertip targets); grasps are sampled around it."""
TIP_RADIUS = 0.014
"""Dome radius (m) of the 'digit360' hand's fingertip geoms (envs/assets/allegro_right_digit360.xml)."""


@dataclass(frozen=True)
class HandVariant:
    """What grasps of a hand variant are generated around, beside its model (hand_spec)."""

    object_start: np.ndarray
    """Nominal object centre (m, world frame), where grasps are generated and the object body is compiled."""
    canonical_pose: np.ndarray
    """The 16 joint angles (rad) grasps are sampled around."""
    tip_radius: float
    """Fingertip dome radius (m): a fingertip within it (and a few mm) of the object touches it."""
    touch_generation: int = 1
    """The simulated Digit 360's model generation (envs.sensors.digit360_model.Digit360Model.generation)."""


VARIANTS: dict[str, HandVariant] = {
    "digit360": HandVariant(OBJECT_START, CANONICAL_POSE, TIP_RADIUS),
    "xela": HandVariant(OBJECT_START, CANONICAL_POSE, TIP_RADIUS),
    "digit360_v4": HandVariant(
        np.array([0.04, 0.0, 0.08]),
        np.array([-0.354, 0.187, 0.459, 1.341, 0.0, 0.212, 0.215, 1.534, 0.356, 0.287, 0.216, 1.515, 1.396, 0.473,
                  0.112, 1.682]),
        0.012, touch_generation=2),
    "xela_v4": HandVariant(
        np.array([0.05, 0.0, 0.08]),
        np.array([-0.332, 0.516, 0.394, 0.418, 0.0, 0.571, 0.079, 0.66, 0.332, 0.599, 0.147, 0.664, 1.089, 0.712, 1.422,
                  -0.106]),
        0.0145, touch_generation=2),
}
"""Hand variants: 'digit360' (Digit 360 fingertips, the default, the model the shipped policies trained on), 'xela'
(stock-length fingertips with Xela shells, and Xela pads on the phalanges and palm: envs.sensors.xela_hand), and
'digit360_v4' (the vendor's published Allegro V4 kinematics with Meta's 12 mm Digit 360 domes, envs.hand_model: the
hand the retrain of issue 72 moves to; its touch renders 12 mm domes), and 'xela_v4' (the same kinematics with the stock
tips under Xela shells and the 18 pads on its own links: envs.sensors.xela_layout.pad_mounts). digit360_v4 holds
the cup lower and closer to the palm, around the pose `python experiments/tools/canonical_pose.py --seed 0` found
(experiments/hand_v4); xela_v4, whose stock-length tips are 26 mm shorter, around the pose of `python
experiments/tools/canonical_pose.py --hand xela_v4 --scale 0.9 --centres-x 0.02 0.03 0.04 0.05 --centres-z 0.05 0.06
0.07 0.08` (experiments/sim_v4)."""
HANDS = tuple(VARIANTS)


def hand_variant(hand: str = DEFAULT_HAND) -> HandVariant:
    """A hand variant (VARIANTS) by name; a ValueError names the known ones."""
    if hand not in VARIANTS:
        raise ValueError(f"unknown hand {hand!r}; hands: {', '.join(HANDS)}")
    return VARIANTS[hand]


def touch_model(hand: str = DEFAULT_HAND) -> Digit360Model:
    """The simulated Digit 360 of a hand variant: its dome radius and model generation ('digit360' renders the
    shipped generation-1 streams bit for bit, the vendor-kinematics hands generation 2)."""
    v = hand_variant(hand)
    return Digit360Model(dome_radius=v.tip_radius, generation=v.touch_generation)


def hand_xml_path() -> str:
    return str(Path(__file__).resolve().parent / "assets" / "allegro_right_digit360.xml")


def hand_spec(hand: str = DEFAULT_HAND) -> mujoco.MjSpec:
    """The spec of a hand variant (one of HANDS), without an object."""
    if hand not in HANDS:
        raise ValueError(f"unknown hand {hand!r}; hands: {', '.join(HANDS)}")
    if hand in ("digit360_v4", "xela_v4"):
        from envs.hand_model import hand_xml

        spec = mujoco.MjSpec.from_string(hand_xml(tips="digit360" if hand == "digit360_v4" else "stock"))
        if hand == "xela_v4":
            from envs.sensors.xela_hand import make_xela_hand

            make_xela_hand(spec, hand)
        return spec
    spec = mujoco.MjSpec.from_file(hand_xml_path())
    if hand == "xela":
        from envs.sensors.xela_hand import make_xela_hand

        make_xela_hand(spec)
    return spec


def build_model(obj: ObjectSpec, scale: float = 1.0, timestep: float = 0.01,
                edit: Callable[[mujoco.MjSpec], None] | None = None, hand: str = DEFAULT_HAND) -> mujoco.MjModel:
    """Compile the hand + object model with the object at ``scale`` (the env's largest).

    ``edit`` may add elements to the finished spec before compiling (e.g. the Digit 360 sensors); ``hand`` picks
    the hand variant (HANDS).
    """
    spec = hand_spec(hand)
    spec.option.timestep = timestep
    body = spec.worldbody.add_body(name=OBJECT_BODY, pos=hand_variant(hand).object_start.tolist())
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


def skin_geoms(m: mujoco.MjModel) -> np.ndarray:
    """The geoms that are skin (the gel domes ``<finger>_tip``, the Xela shells and pads ``xela_*``): on the
    hardware's physics they take the fingertips' friction, the rest of the hand the links' one."""
    skin = {f"{finger}_tip" for finger in FINGERS}
    return np.array([g for g in range(m.ngeom) if m.geom(g).name in skin or m.geom(g).name.startswith("xela_")])


def link_geoms(m: mujoco.MjModel, obj_geoms: np.ndarray) -> np.ndarray:
    """The colliding geoms of the hand that are not skin (finger links, sensor housings, palm): the ones with the
    links' own friction where the hardware's physics draws one (EnvConfig's ``link_friction``)."""
    return np.setdiff1d(np.flatnonzero(m.geom_contype > 0), np.r_[skin_geoms(m), obj_geoms])
