"""Measured object properties: the keys of a session's ``properties`` that stand in for the privileged vector.

A session's metadata (rotation.data.session, ``properties``) holds what is known about the object. For the
privileged vector (envs.constants.PRIV_FIELDS) these keys are read, in SI units:

============  =====  ============================================================================================
key           size   meaning
============  =====  ============================================================================================
``scale``     1      object size relative to the simulated base cup (envs.objects ``cup``: body radius 40 mm,
                     body height 85 mm), e.g. a cup of radius 32 mm is 0.8
``mass``      1      kg, everything that moves with the object (added weights included)
``friction``  1      sliding friction coefficient between the object's surface and the fingertip material
``com``       3      m, center of mass minus the center of the cup's body (object frame: z along the cup's axis,
                     up; y toward the handle), e.g. [0, 0, 0.01] for a weight 1 cm above the middle
============  =====  ============================================================================================

The object *position* (PRIV_FIELDS pos_x, pos_y, pos_z) is not a property: it changes every step and a real hand
does not measure it (adapters.real_data says what stands in for it). Simulated sessions store the same keys with
the simulated values (``rotate collect``, ``rotate deploy`` on an emulated hand); other keys (``grasp``, notes) are
allowed and ignored here.

``rotate deploy --properties mass=0.12,friction=0.8,com=0,0,0.01,scale=0.8`` writes them into a recording.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

PROPERTY_SIZES: dict[str, int] = {"scale": 1, "mass": 1, "friction": 1, "com": 3}
"""Measured property -> number of values."""
PROPERTY_LIMITS: dict[str, tuple[float, float]] = {
    "scale": (0.1, 3.0),  # envs.config's bounds on randomization.scales
    "mass": (0.0, 2.0),  # kg, open at 0; 2 kg is four times what the 0.5 N m actuators lift: a unit slip (g)
    "friction": (0.0, 5.0),  # open at 0; above 5 no surface of a handheld object is plausibly measured
    "com": (-0.1, 0.1),  # m per axis: a cup is < 10 cm across; larger values are a unit slip (cm, mm)
}
"""Plausible ranges (catch typos and unit slips, not values outside the teacher's training ranges)."""
PROPERTY_UNITS = {"scale": "", "mass": "kg", "friction": "", "com": "m"}


def check_properties(props: Mapping[str, Any], where: str) -> dict[str, float | list[float]]:
    """The measured properties of ``props`` (any other keys are ignored), checked: every key of PROPERTY_SIZES
    present, with the right number of finite values in PROPERTY_LIMITS. ValueError naming ``where`` and the key."""
    missing = [k for k in PROPERTY_SIZES if k not in props]
    if missing:
        have = ", ".join(sorted(props)) or "none"
        raise ValueError(f"{where}: missing measured object propert{'ies' if len(missing) > 1 else 'y'} "
                         f"{', '.join(missing)} (has: {have}); the privileged vector needs "
                         f"{', '.join(PROPERTY_SIZES)} (rotation.data.properties)")
    return {k: check_value(k, props[k], where) for k in PROPERTY_SIZES}


def check_value(key: str, value: Any, where: str) -> float | list[float]:
    """One property's value (``key`` of PROPERTY_SIZES) checked: its count of finite numbers within PROPERTY_LIMITS;
    ValueError naming ``where`` and the key."""
    n = PROPERTY_SIZES[key]
    values = value if isinstance(value, list | tuple) else [value]
    if len(values) != n or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in values):
        want = "a number" if n == 1 else f"{n} numbers"
        raise ValueError(f"{where}: property {key!r} must be {want}, got {value!r}")
    lo, hi = PROPERTY_LIMITS[key]
    open_low = key in ("mass", "friction")
    for x in values:
        if not (math.isfinite(x) and (x > lo if open_low else x >= lo) and x <= hi):
            unit = f" {PROPERTY_UNITS[key]}" if PROPERTY_UNITS[key] else ""
            raise ValueError(f"{where}: property {key!r} = {value!r} is outside {'(' if open_low else '['}{lo:g}, "
                             f"{hi:g}]{unit}")
    out = [float(x) for x in values]
    return out[0] if n == 1 else out


def parse_properties(spec: str, where: str = "properties") -> dict[str, float | list[float]]:
    """``'mass=0.12,friction=0.8,com=0,0,0.01,scale=0.8'`` -> {key: value}; the values that follow a ``com=`` are its
    three numbers. An empty spec is {}; a spec names each key at most once, and every key it names is checked
    (ValueError naming ``where``); it need not name them all."""
    spec = spec.strip()
    if not spec:
        return {}
    form = "give KEY=VALUE pairs, e.g. mass=0.12,friction=0.8,com=0,0,0.01,scale=0.8"
    parts: list[tuple[str, list[str]]] = []
    for token in (t.strip() for t in spec.split(",")):
        if "=" in token:
            key, value = (x.strip() for x in token.split("=", 1))
            if key not in PROPERTY_SIZES:
                raise ValueError(f"{where}: unknown property {key!r}; known: {', '.join(PROPERTY_SIZES)}")
            if any(k == key for k, _ in parts):
                raise ValueError(f"{where}: property {key!r} given twice")
            parts.append((key, [value]))
        elif parts and token:
            parts[-1][1].append(token)  # the next value of a vector property (com=x,y,z)
        else:
            raise ValueError(f"{where}: cannot read {spec!r}; {form}")
    out: dict[str, float | list[float]] = {}
    for key, texts in parts:
        try:
            numbers = [float(t) for t in texts]
        except ValueError:
            raise ValueError(f"{where}: property {key!r} = {','.join(texts)!r} is not a number; {form}") from None
        out[key] = check_value(key, numbers if PROPERTY_SIZES[key] > 1 else
                                (numbers[0] if len(numbers) == 1 else numbers), where)
    return out
