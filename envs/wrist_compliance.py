"""A compliant wrist for the insertion task (envs.insertion): the arm that carries the hand yields to the forces the
socket puts on the plug, as a robot arm under Cartesian admittance control with a wrist force/torque sensor does.

Without it the wrist follows its target through a stiff weld (envs.held_hand: 0.5 mm of sag under the hand's
weight, about 19 kN/m), so a target a millimetre past the plate presses tens of newtons, and a policy's small
position errors become presses that the fingertip grip cannot hold (experiments/insertion: the imitation policies
pressed about four times harder than the expert before the plug slipped). Robot arms that insert by contact run
in impedance or admittance control at translational stiffnesses of a few hundred to a few thousand N/m.

Two settings (``InsertionConfig.wrist``):

- ``stiff`` (FIRST_WRIST, the runs recorded before the setting): the weld's target jumps to each action's pose at
  the action's start;
- ``compliant``: the target moves there at constant speed over the action (an arm follows a trajectory, it does not
  teleport: a 3 mm jump drove the hand into the plate at tenths of a metre per second), and the arm yields: the
  measured external force F on the plug (the socket's contacts, the only external contacts of the hand and plug)
  drives a virtual mass-spring-damper per world axis, ``M x'' + D x' + K x = F``, and the weld's target is the
  commanded pose moved by x (translation only; the orientation stays stiff). At rest against the plate the press is
  ``K`` times how far the command is past where the prong stops: STIFFNESS along the socket's axis (world z, the
  socket tilts at most 3 degrees), LATERAL_STIFFNESS across it, ``M`` = MASS, ``D`` critically damped.

Measured (seeds 200-203, the prong moved 5 mm sideways from under the hole and pushed onto the plate, 1 mm per
action, then 3 mm per action for three actions): the stiff wrist pressed 15-17 N at the end and the plug moved
5-11 mm in the fingertips; the ramped target alone 10-12 N and 3-10 mm; ramped and compliant 2.2-4.1 N and under
1 mm.
"""

from __future__ import annotations

import math

import numpy as np

WRISTS = ("stiff", "compliant")
FIRST_WRIST = "stiff"
"""The wrist of the demonstrations and policies recorded before the wrist was a setting."""
STIFFNESS = 300.0
"""Stiffness (N/m) of the compliant wrist along the socket's axis: 0.3 N per millimetre of the command past where
the prong stops, at the soft end of what robot arms' Cartesian impedance controllers use for contact tasks (a few
hundred to a few thousand N/m)."""
LATERAL_STIFFNESS = 1000.0
"""Stiffness (N/m) across the socket's axis: stiffer, so that the friction of a press on the plate (0.3 of it)
moves the prong sideways by tenths of a millimetre, not the hole's 1 mm clearance."""
MASS = 0.3
"""Virtual mass (kg) of the admittance: with the stiffnesses a 5-9 Hz response, ten times slower than the weld's
5 ms time constant, so the loop through the stiff plate stays stable."""
MAX_OFFSET = 0.05
"""Largest yield (m): an arm's controller bounds how far its admittance may move it from the command."""


def check_wrist(where: str, wrist: str) -> None:
    if wrist not in WRISTS:
        raise ValueError(f"{where}: wrist must be one of {', '.join(WRISTS)}, got {wrist!r}")


def wrist_model(wrist: str) -> CompliantWrist:
    """The admittance of setting ``wrist`` (a stiff one has none and does not ramp)."""
    check_wrist("wrist_model", wrist)
    if wrist == "stiff":
        return CompliantWrist(0.0, 0.0, ramps=False)
    return CompliantWrist(STIFFNESS, LATERAL_STIFFNESS, MASS, ramps=True)


class CompliantWrist:
    """The admittance's state (module docstring). ``stiffness`` 0: no compliance (the offset stays 0)."""

    def __init__(self, stiffness: float, lateral: float | None = None, mass: float = MASS, ramps: bool = True) -> None:
        lateral = stiffness if lateral is None else lateral
        for what, value in (("stiffness", stiffness), ("lateral stiffness", lateral)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"wrist {what} must be a finite number of N/m >= 0, got {value!r}")
        if (stiffness > 0.0) != (lateral > 0.0):
            raise ValueError("wrist: give both stiffnesses, or neither (0: the stiff wrist)")
        if not (math.isfinite(mass) and mass > 0.0):
            raise ValueError(f"wrist admittance mass must be a positive number of kg, got {mass!r}")
        self.stiffness = np.array([lateral, lateral, stiffness], dtype=float)
        """Per world axis (N/m): x and y across the socket's axis, z along it."""
        self.mass = float(mass)
        self.ramps = bool(ramps)
        """Whether the arm moves the target over each action (True) or jumps to it (the stiff wrist)."""
        self.damping = 2.0 * np.sqrt(self.stiffness * self.mass)
        self.offset = np.zeros(3)
        """How far (m, world) the wrist has yielded from its command."""
        self.velocity = np.zeros(3)

    @property
    def active(self) -> bool:
        return bool(self.stiffness[2] > 0.0)

    def reset(self) -> None:
        self.offset[:] = 0.0
        self.velocity[:] = 0.0

    def update(self, force: np.ndarray, dt: float) -> None:
        """Advance the admittance by ``dt`` s under the external ``force`` (N, world): semi-implicit Euler, the
        spring and damper taken at the new velocity (stable for any dt at these gains)."""
        if not self.active:
            return
        k, c, m = self.stiffness, self.damping, self.mass
        # v' = (F - c v' - k (x + dt v')) / m  ->  solve for the new velocity, then x += dt v'
        self.velocity = (m * self.velocity + dt * (np.asarray(force, dtype=float) - k * self.offset)) / (
            m + dt * c + dt * dt * k)
        self.offset = self.offset + dt * self.velocity
        n = float(np.linalg.norm(self.offset))
        if n > MAX_OFFSET:
            self.offset *= MAX_OFFSET / n
            self.velocity[:] = 0.0
