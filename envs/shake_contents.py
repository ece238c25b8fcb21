"""What a shaken bottle holds, as MuJoCo can simulate it honestly: grains as rigid bodies of their real size, density
and friction; a liquid as the equivalent mechanical model of its first sloshing mode.

Granular contents (pills, rice, lentils) fill the bottle like the liquids, to a fraction of its inner height, at the
mass a real pour has there: the grain's true density times a packing fraction of 0.6 (the solid share of a poured
granular bed: random loose packing of spheres is about 0.55, random close packing 0.64; taken for capsules and
lenses as well, an assumption). At their real size such a fill is hundreds to thousands of grains (rice), which 2 CPU
cores cannot step at the rate the fingertips' IMU needs, so the fill is **coarse-grained** (the scaled-particle
practice of discrete element models): it is simulated as a fixed number of parcels per level (8, 16, 32), each the
real grain scaled up in every dimension by the same factor, of the grain's true density, so that the parcels
together carry the fill's mass. What the hand feels then has the real content's mass and the grain's shape, density
and friction; the size of one impact is a parcel's, not a grain's (a rattle of few heavy pieces rather than a hiss of
many light ones). Before this, the fills were 3 to 50 grains at their real size: 1-8 g of rice, lentils or pills
against 11-231 g of liquid, and neither a probe nor the fingertips' contact forces could tell the contents apart.
Sizes, densities and friction of one grain (typical values; each figure's source beside it):

- pills: a size-0 hard capsule, 21.7 mm long and 7.6 mm across (the standard capsule size table: size 0 is
  21.7 mm closed length, 7.64 mm body diameter), filled to about 0.5 g: a capsule geom of that length and radius,
  density from that mass; friction 0.3 (gelatin on plastic, an assumption);
- rice: a long-grain milled kernel, about 6.8 x 2 mm (long-grain rice: length above 6.6 mm, length/width above 3,
  the USDA grade standard's classes), kernel density about 1.45 g/cm3 (true density of milled rice, 1.4-1.5 g/cm3 in
  grain-handling tables): a capsule of radius 1 mm and that length; friction 0.35 (rice on plastic, 0.3-0.4 in
  grain-handling tables);
- lentils: a red lentil, a lens about 4.5 mm across and 2 mm thick, density about 1.35 g/cm3: a sphere of the lens's
  volume (radius 1.7 mm: the lens's shape is left out, a sphere steps fastest); friction 0.35.

Liquids (water, oil) fill the bottle to a fraction of its inner height. Their first antisymmetric sloshing mode in
an upright cylinder of radius R, filled to depth h, has the angular frequency ``w^2 = (g xi / R) tanh(xi h / R)``,
``xi = 1.8412`` the first root of J1' (the linear theory of sloshing in cylindrical tanks, e.g. Ibrahim, "Liquid
Sloshing Dynamics", 2005, ch. 2; Abramson, NASA SP-106, 1966). Its equivalent pendulum (NASA SP-106, ch. 6) carries
the moving mass ``m1 = m (2 R / (xi (xi^2 - 1) h)) tanh(xi h / R)`` on a rod of length ``L1 = g / w^2``; the rest,
``m0 = m - m1``, moves with the bottle. The damping of that mode is the logarithmic decrement of Stephens et al.
(1962, quoted in NASA SP-106, ch. 4): ``delta = 4.98 nu^0.5 R^-0.75 g^-0.25 (1 + (0.318 / sinh(1.84 h/R)) (1 + (1 -
h/R) / cosh(1.84 h/R)))``, with the kinematic viscosity ``nu``: water 1.0e-6 m2/s and olive oil 9.2e-5 m2/s at 20 C
(dynamic viscosities 1.0 and 84 mPa s, densities 998 and 915 kg/m3, CRC Handbook of Chemistry and Physics). Left
out: higher modes, swirl, the free surface breaking, and the pendulum's hinge height (the model hangs it so that
the moving mass rests at the liquid's centroid, keeping the bottle's centre of mass where the liquid puts it); the
pendulum swings at most 60 degrees, where it meets a joint limit as the liquid meets the wall.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

G = 9.81
"""Gravity (m/s^2)."""
XI = 1.8412
"""First root of J1', the first antisymmetric sloshing mode of an upright cylinder."""
FILL_LEVELS = ("few", "some", "many")
"""Fill level labels, lowest first (class ids 0, 1, 2)."""


PACKING = 0.6
"""Solid fraction of a poured granular content (module docstring)."""
FILLS = (0.1, 0.25, 0.45)
"""Fill depth per level (FILL_LEVELS), as a fraction of the bottle's inner height: liquids and grains alike."""
PARCELS = (8, 16, 32)
"""Simulated parcels per fill level of a granular content (module docstring)."""


@dataclass(frozen=True)
class Grain:
    """One kind of granular content: a capsule (``half_length`` > 0) or a sphere, the size of one real grain."""

    radius: float
    """m."""
    half_length: float
    """Half the capsule's cylindrical part (m); 0 for a sphere."""
    density: float
    """kg/m^3."""
    friction: float
    fills: tuple[float, float, float] = FILLS
    """Fill depth per level, as a fraction of the bottle's inner height."""
    parcels: tuple[int, int, int] = PARCELS
    """Simulated parcels per fill level."""

    @property
    def volume(self) -> float:
        return math.pi * self.radius**2 * 2 * self.half_length + 4 / 3 * math.pi * self.radius**3

    @property
    def mass(self) -> float:
        """One real grain's mass (kg)."""
        return self.density * self.volume

    def fill_mass(self, inner_r: float, inner_h: float, level: int) -> float:
        """The mass (kg) of a pour filling an upright cylinder of inner radius and height (m) to ``level``."""
        return self.density * PACKING * math.pi * inner_r**2 * self.fills[level] * inner_h


@dataclass(frozen=True)
class Liquid:
    """One liquid: density and kinematic viscosity at 20 C."""

    density: float
    """kg/m^3."""
    viscosity: float
    """Kinematic viscosity (m^2/s)."""
    fills: tuple[float, float, float] = FILLS
    """Depth per fill level, as a fraction of the bottle's inner height."""


_CAPSULE_R, _CAPSULE_HALF = 0.00382, (0.0217 - 2 * 0.00382) / 2
CONTENTS: dict[str, Grain | Liquid] = {
    "pills": Grain(_CAPSULE_R, _CAPSULE_HALF, 0.0005 / (math.pi * _CAPSULE_R**2 * 2 * _CAPSULE_HALF
                                                       + 4 / 3 * math.pi * _CAPSULE_R**3), 0.3),
    "rice": Grain(0.001, (0.0068 - 0.002) / 2, 1450.0, 0.35),
    "lentils": Grain(0.0017, 0.0, 1350.0, 0.35),
    "water": Liquid(998.0, 1.0e-6),
    "oil": Liquid(915.0, 9.2e-5),
}
"""Content name -> its physics (the module docstring gives the sources). Class ids follow this order."""
CONTENT_NAMES = tuple(CONTENTS)


@dataclass(frozen=True)
class Slosh:
    """The equivalent pendulum of a liquid's first sloshing mode (module docstring)."""

    mass: float
    """The liquid's mass (kg)."""
    moving_mass: float
    """m1 (kg): swings on the pendulum."""
    length: float
    """L1 (m)."""
    omega: float
    """Natural angular frequency (rad/s)."""
    damping_ratio: float
    """zeta = delta / (2 pi)."""
    depth: float
    """Liquid depth h (m)."""

    @property
    def hinge_damping(self) -> float:
        """Rotational damping (N m s/rad) of each of the pendulum's two hinges: 2 zeta w m1 L1^2."""
        return 2 * self.damping_ratio * self.omega * self.moving_mass * self.length**2


def slosh_model(liquid: Liquid, radius: float, depth: float) -> Slosh:
    """The sloshing pendulum of ``liquid`` in an upright cylinder of inner ``radius`` filled to ``depth`` (m)."""
    if radius <= 0 or depth <= 0:
        raise ValueError(f"slosh_model: radius and depth must be > 0 m, got {radius}, {depth}")
    r, h = radius, depth
    th = math.tanh(XI * h / r)
    omega = math.sqrt(G * XI / r * th)
    mass = liquid.density * math.pi * r**2 * h
    moving = min(mass, mass * 2 * r / (XI * (XI**2 - 1) * h) * th)
    x = 1.84 * h / r
    delta = 4.98 * liquid.viscosity**0.5 * r**-0.75 * G**-0.25 * (1 + 0.318 / math.sinh(x) * (1 + (1 - h / r)
                                                                                                 / math.cosh(x)))
    return Slosh(mass, moving, G / omega**2, omega, delta / (2 * math.pi), h)
