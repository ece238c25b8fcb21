"""Object registry: Hora's cylinder family and cups with a handle.

Each object is described at scale 1.0 in meters; the env scales it per simulation (docs/reference/hora.md: scale
0.70..0.86). Objects are added to the hand model with MjSpec so the hand MJCF stays a plain, readable file.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np


@dataclass(frozen=True)
class ObjectSpec:
    """Geometry of one rotatable object at scale 1.0 (meters, kilograms)."""

    name: str
    kind: str
    """'cylinder' (axis horizontal, along the hand's y axis, as in Hora) or 'cup' (upright body with a handle)."""
    radius: float
    length: float
    """Cylinder length, or the cup's body height."""
    handle: bool = False

    def geoms(self, scale: float) -> list[dict]:
        """Primitive geoms (type, size, pos, quat) of the object at a given scale, in the object frame."""
        r, h = self.radius * scale, self.length * scale
        if self.kind == "cylinder":
            # axis along y: rotate the z-aligned cylinder by 90 deg about x
            quat = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0])
            return [dict(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[r, h / 2, 0], pos=[0, 0, 0], quat=quat)]
        geoms = [dict(type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[r, h / 2, 0], pos=[0, 0, 0], quat=[1, 0, 0, 0])]
        if self.handle:
            # a C-shaped handle from three capsules on the +y side of the cup body (away from fingers and thumb)
            t, out = 0.18 * r, 0.45 * r
            along_y = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]  # capsule axis z -> y
            geoms += [
                dict(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[t / 2, out / 2, 0], pos=[0, r + out / 2, 0.3 * h],
                     quat=along_y),
                dict(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[t / 2, out / 2, 0], pos=[0, r + out / 2, -0.3 * h],
                     quat=along_y),
                dict(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[t / 2, 0.3 * h, 0], pos=[0, r + out, 0],
                     quat=[1, 0, 0, 0]),
            ]
        return geoms


def _cylinders() -> dict[str, ObjectSpec]:
    # Hora's nine training cylinders: radius 4 cm, lengths 6.4 .. 9.6 cm (docs/reference/hora.md)
    lengths = np.linspace(0.064, 0.096, 9)
    return {f"cylinder_{i}": ObjectSpec(f"cylinder_{i}", "cylinder", 0.04, float(length))
            for i, length in enumerate(lengths)}


OBJECTS: dict[str, ObjectSpec] = {
    **_cylinders(),
    "cylinder": ObjectSpec("cylinder", "cylinder", 0.04, 0.080),
    "cup_small": ObjectSpec("cup_small", "cup", 0.036, 0.075, handle=True),
    "cup": ObjectSpec("cup", "cup", 0.040, 0.085, handle=True),
    "cup_large": ObjectSpec("cup_large", "cup", 0.044, 0.095, handle=True),
}
"""Name -> object. 'cylinder' is the middle of Hora's family; 'cup' is the default task object."""


def get_object(name: str) -> ObjectSpec:
    """Look up an object by name; raises ValueError listing the known names."""
    try:
        return OBJECTS[name]
    except KeyError:
        raise ValueError(f"unknown object {name!r}; known objects: {', '.join(sorted(OBJECTS))}") from None
