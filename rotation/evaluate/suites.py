"""Evaluation conditions: named perturbations of the env, grouped into suites.

A condition is a :class:`envs.config.Perturbation` applied on top of whatever the env would otherwise use
(friction x scale, mass + kg, CoM + m). Suites are an explicit registry; asking for an unknown suite or condition
raises an error that lists the valid names.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from envs.config import MAX_OBJECT_MASS, Perturbation, default_randomization
from envs.constants import DEFAULT_HAND

NOMINAL = "nominal"


@dataclass(frozen=True)
class Condition:
    """One evaluation condition."""

    name: str
    """Short unique name, used in tables, plots and video file names."""
    perturb: Perturbation

    @property
    def axis(self) -> str:
        """Which perturbation it varies: 'nominal', 'friction', 'mass', 'com' or 'combined' (several at once)."""
        p = self.perturb
        varied = [a for a, on in (("friction", p.friction_scale != 1.0), ("mass", p.added_mass != 0.0),
                                  ("com", any(p.com_shift))) if on]
        return NOMINAL if not varied else varied[0] if len(varied) == 1 else "combined"


def axis_level(cond: Condition, axis: str) -> float:
    """Position of ``cond`` on a plot axis: friction scale, added mass (kg) or CoM shift norm (m)."""
    p = cond.perturb
    if axis == "friction":
        return p.friction_scale
    if axis == "mass":
        return p.added_mass
    if axis == "com":
        return float(sum(c * c for c in p.com_shift) ** 0.5)
    return 0.0


def condition_name(p: Perturbation) -> str:
    """A file-name-safe name: 'friction_0.5', 'mass_+0.1kg', 'com_0.01_0_0', 'friction_0.5+mass_+0.1kg'."""
    parts = []
    if p.friction_scale != 1.0:
        parts.append(f"friction_{p.friction_scale:g}")
    if p.added_mass != 0.0:
        parts.append(f"mass_+{p.added_mass:g}kg")
    if any(p.com_shift):
        parts.append("com_" + "_".join(f"{c:g}" for c in p.com_shift))
    return "+".join(parts) or NOMINAL


def make_condition(p: Perturbation) -> Condition:
    return Condition(condition_name(p), p)


def _perturbations_suite(hand: str = DEFAULT_HAND) -> list[Condition]:
    # Sparsh-X reports robustness to reduced friction and added mass without levels (docs/reference/sparsh.md); ours
    # go from mild to a quarter of the friction, up to +0.2 kg (about the top of the shipped physics' mass range,
    # 0.25 kg, docs/reference/hora.md) where the hand's heaviest cup leaves room for it under MAX_OBJECT_MASS (the
    # hardware physics' cups reach 0.4 kg: up to +0.1 kg there), and CoM shifts of one and two times the training
    # range (+-1 cm)
    room = MAX_OBJECT_MASS - default_randomization(hand).mass[1]
    perturbs = [Perturbation()]
    perturbs += [Perturbation(friction_scale=f) for f in (0.75, 0.5, 0.35, 0.25)]
    perturbs += [Perturbation(added_mass=m) for m in (0.05, 0.1, 0.2) if m <= room + 1e-9]
    perturbs += [Perturbation(com_shift=(d, 0.0, 0.0)) for d in (0.01, 0.02)]
    perturbs += [Perturbation(friction_scale=0.5, added_mass=0.1)]
    return [make_condition(p) for p in perturbs]


SUITES: dict[str, Callable[[str], list[Condition]]] = {
    "perturbations": _perturbations_suite,
    NOMINAL: lambda hand: [make_condition(Perturbation())],
}
"""Suite name -> factory of its conditions on a hand variant (its physics bound the added mass)."""


def get_suite(name: str, only: Sequence[str] = (), hand: str = DEFAULT_HAND) -> list[Condition]:
    """The conditions of suite ``name`` on ``hand``, optionally restricted to the names in ``only`` (in suite
    order)."""
    if name not in SUITES:
        raise ValueError(f"unknown suite {name!r}; choose one of: {', '.join(SUITES)}")
    conds = SUITES[name](hand)
    if only:
        known = [c.name for c in conds]
        unknown = [o for o in only if o not in known]
        if unknown:
            raise ValueError(f"unknown condition(s) {unknown} in suite {name!r}; its conditions are: "
                             f"{', '.join(known)}")
        conds = [c for c in conds if c.name in only]
    return conds
