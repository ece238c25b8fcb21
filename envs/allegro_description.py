"""The right Allegro hand (V4) as its vendor describes it, and the Digit 360 fingertip mount: figures as data.

Every number here is a published figure (docs/reference/hora.md, "Allegro hand facts"): the vendor's
allegro_hand_description (v4), whose figures Hora's allegro.urdf and MuJoCo Menagerie's wonik_allegro repeat, and
Meta's facebookresearch/digit360 model of the Allegro with Digit 360 fingertips (meshes/digit360_allegro_right.urdf;
its figures only, not its meshes). Where a figure is not published, the field says what stands in for it.

Frames are the vendor's palm frame: the fingers extend along +z, the palm normal is +x (the fingers curl toward
+x), the index finger is on +y. Lengths in m, angles in rad; a joint's origin is given in its parent link's frame
as xyz and URDF rpy (roll about x, then pitch about y, then yaw about z, i.e. R = Rz(yaw) Ry(pitch) Rx(roll)), its
axis in its own link's frame. envs.hand_model builds the MuJoCo model from this module; tests/envs/test_hand_model.py
holds that model to these figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envs import constants as C


@dataclass(frozen=True)
class Link:
    """One moving link: the joint that moves it and the link's collision box and mass."""

    joint: str
    """Joint name in this project's bus order naming (``<finger>_<0..3>``, envs.constants.JOINT_NAMES)."""
    origin: tuple[float, float, float]
    """Joint origin in the parent link's frame (m)."""
    rpy: tuple[float, float, float]
    """Joint frame orientation relative to the parent link (URDF roll, pitch, yaw; rad)."""
    axis: tuple[float, float, float]
    """Joint axis in the link's own frame."""
    box: tuple[float, float, float]
    """Collision box, full size (x thickness, y width, z length; m)."""
    box_center: tuple[float, float, float]
    """Collision box centre in the link's frame (m)."""
    mass: float
    """Link mass (kg)."""


FINGER_BOX = (0.0196, 0.0275)
"""Finger link cross-section (x thickness, y width; m): every finger link and thumb links 13-15."""

FINGER_ORIGINS = {
    "index": ((0.0, 0.0435, -0.001542), (-0.0873, 0.0, 0.0)),
    "middle": ((0.0, 0.0, 0.0007), (0.0, 0.0, 0.0)),
    "ring": ((0.0, -0.0435, -0.001542), (0.0873, 0.0, 0.0)),
}
"""Joint 0 origin (xyz, rpy) of each finger on the palm: index and ring turned 5 degrees (0.0873 rad) outward."""

ROLL_LEN, PROXIMAL_LEN, MEDIAL_LEN = 0.0164, 0.054, 0.0384
"""Finger link lengths (m): joint 0 -> 1, 1 -> 2, 2 -> 3."""

THUMB_ORIGIN = ((-0.0182, 0.019333, -0.045987), (0.0, -1.658063, -1.570796))
"""Thumb joint 12 origin (xyz, rpy) on the palm."""
THUMB_13_ORIGIN = (-0.027, 0.005, 0.0399)
"""Thumb joint 13 origin in link 12's frame (m)."""
THUMB_LEN_13, THUMB_LEN_14 = 0.0177, 0.0514
"""Thumb link lengths (m): joint 13 -> 14, 14 -> 15."""

LINK_MASS = {"base": 0.0119, "proximal": 0.065, "medial": 0.0355, "distal": 0.0096}
"""Finger link masses (kg): roll (joint 0) link, proximal, medial, distal (without the tip)."""
THUMB_MASS = (0.0176, 0.0119, 0.038, 0.0388)
"""Thumb link masses (kg), links 12-15 (15 without the tip)."""

PALM_BOX = (0.0408, 0.1130, 0.095)
"""Palm collision box, full size (m); its front face is 11 mm in front of the finger roll axes."""
PALM_BOX_CENTER = (-0.0093, 0.0, -0.0475)
PALM_MASS = 0.415

THUMB_BASE_BOX = (0.0358, 0.034, 0.0455)
"""Thumb link 12's collision box (full size). Its centre is not among the published figures: it stands midway
between joint 12's and joint 13's origins (THUMB_BASE_BOX_CENTER)."""
THUMB_BASE_BOX_CENTER = (THUMB_13_ORIGIN[0] / 2, THUMB_13_ORIGIN[1] / 2, THUMB_13_ORIGIN[2] / 2)

# The Digit 360 fingertip (Meta's Allegro + Digit 360 model)
DIGIT360_MOUNT = {"finger": 0.020, "thumb": 0.0353}
"""The sensor's base, along the last link past joint 3 / 7 / 11 (finger) and past joint 15 (thumb) (m); the stock
tips are removed."""
DIGIT360_DOME_OFFSET = 0.037
"""The dome's centre past the sensor's base (m): a sphere fitted to the published tip mesh."""
DIGIT360_DOME_RADIUS = 0.012
DIGIT360_BODY = (0.028, 0.028, 0.032)
"""The sensor body (x, y, z full size, m): 28 x 28 mm across, 32 mm along the finger."""
DIGIT360_MASS = 0.0168
"""Not published: the stock tip's mass (kg) stands in for the sensor's."""


# The stock fingertip (the vendor's description), which the Xela hand's fingertip shells replace
STOCK_TIP_OFFSET = {"finger": 0.0267, "thumb": 0.0423}
"""The stock tip sphere's centre along the last link past joint 3 / 7 / 11 (finger) and past joint 15 (thumb) (m)."""
STOCK_TIP_RADIUS = 0.012
STOCK_TIP_MASS = 0.0168


def dome_offset(finger: str) -> float:
    """Distance of a fingertip's dome centre past the finger's last joint (m): 0.057 for a finger, 0.0723 for the
    thumb."""
    return DIGIT360_MOUNT["thumb" if finger == "thumb" else "finger"] + DIGIT360_DOME_OFFSET


def _centred(length: float) -> tuple[float, float, float]:
    return (0.0, 0.0, length / 2)


def finger_links(finger: str) -> tuple[Link, ...]:
    """The four links of a finger (joints 0-3) or of the thumb (joints 12-15), from the palm outward; the last
    link's box is the distal link up to the Digit 360's base (where a stock tip or a Xela shell begins too)."""
    if finger not in C.FINGERS:
        raise ValueError(f"unknown finger {finger!r}; fingers: {', '.join(C.FINGERS)}")
    w = FINGER_BOX
    if finger == "thumb":
        mount = DIGIT360_MOUNT["thumb"]
        (xyz, rpy) = THUMB_ORIGIN
        return (
            Link("thumb_0", xyz, rpy, (-1.0, 0.0, 0.0), THUMB_BASE_BOX, THUMB_BASE_BOX_CENTER, THUMB_MASS[0]),
            Link("thumb_1", THUMB_13_ORIGIN, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (*w, THUMB_LEN_13),
                 _centred(THUMB_LEN_13), THUMB_MASS[1]),
            Link("thumb_2", (0.0, 0.0, THUMB_LEN_13), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (*w, THUMB_LEN_14),
                 _centred(THUMB_LEN_14), THUMB_MASS[2]),
            Link("thumb_3", (0.0, 0.0, THUMB_LEN_14), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (*w, mount),
                 _centred(mount), THUMB_MASS[3]),
        )
    xyz, rpy = FINGER_ORIGINS[finger]
    mount = DIGIT360_MOUNT["finger"]
    zero = (0.0, 0.0, 0.0)
    return (
        Link(f"{finger}_0", xyz, rpy, (0.0, 0.0, 1.0), (*w, ROLL_LEN), _centred(ROLL_LEN), LINK_MASS["base"]),
        Link(f"{finger}_1", (0.0, 0.0, ROLL_LEN), zero, (0.0, 1.0, 0.0), (*w, PROXIMAL_LEN), _centred(PROXIMAL_LEN),
             LINK_MASS["proximal"]),
        Link(f"{finger}_2", (0.0, 0.0, PROXIMAL_LEN), zero, (0.0, 1.0, 0.0), (*w, MEDIAL_LEN), _centred(MEDIAL_LEN),
             LINK_MASS["medial"]),
        Link(f"{finger}_3", (0.0, 0.0, MEDIAL_LEN), zero, (0.0, 1.0, 0.0), (*w, mount), _centred(mount),
             LINK_MASS["distal"]),
    )


def rpy_matrix(rpy: tuple[float, float, float]) -> np.ndarray:
    """URDF rpy -> rotation matrix R = Rz(yaw) Ry(pitch) Rx(roll) (3, 3)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


PALM_IN_WORLD = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
"""Rotation from the vendor's palm frame to the env's world frame (palm up): the fingers (+z) point along world
+x, the palm normal (+x) along world +z, the index side (+y) along world -y. A half turn about (1, 0, 1)/sqrt(2)."""
PALM_QUAT = (0.0, float(np.sqrt(0.5)), 0.0, float(np.sqrt(0.5)))
"""PALM_IN_WORLD as a MuJoCo quaternion (w, x, y, z)."""
