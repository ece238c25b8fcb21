"""What a policy bundle's config must satisfy before anything acts on it (evaluation, the demo, a real hand).

A bundle's config.json is data from disk: a hand-edited or foreign file can hold a number as a string, inverted
joint limits or a control rate no hand can follow. :class:`rotation.policy.bundle_config.BundleConfig` runs these checks
when it is built, so ``PolicyBundle.load`` refuses such a bundle with a message naming the field, before a simulation
starts or a motor is switched on. Both functions return problems as text (empty: fine); the bundle module turns
them into a ``BundleError``.

Ranges (inclusive) and why:

- ``control_hz`` in :data:`CONTROL_HZ_RANGE`;
- ``action_scale`` in (0, :data:`MAX_ACTION_SCALE`] rad per step;
- ``joint_lower`` < ``joint_upper``, both finite and inside the Allegro hand's limits (``envs.constants``, the same
  values the drivers' safety layer clamps to), within :data:`LIMIT_TOLERANCE`;
- ``action_dim`` = 16 (the RotateCup-v0 action); every network size >= 1.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from typing import Any, Literal

import numpy as np

from envs import constants as C

CONTROL_HZ_RANGE = (5.0, 100.0)
"""Control rates (Hz) a bundle may declare. Above 100 Hz no hand follows: the LEAP driver writes goals at 100 Hz
(``LeapConfig.loop_hz``) and deploy must fit a policy call into ``policy_budget`` of a period. Below 5 Hz the
drivers' watchdog (5 control periods, rotation.deploy.hands) would let a stalled loop go on for over a second,
longer than deploy's default ``hold_limit_s``."""
MAX_ACTION_SCALE = 0.25
"""Largest joint-target change per unit action (rad per step). The env's default is 1/24 rad (Hora's); at 0.25 rad
a single action covers a quarter of the narrowest joint range (finger abduction, 0.94 rad)."""
LIMIT_TOLERANCE = 1e-6
"""Slack (rad) on the hand's joint limits for values that went through a float round trip."""


def type_problems(obj: Any, prefix: str = "") -> list[str]:
    """Fields of the dataclass ``obj`` (nested config dataclasses included) whose value does not have the declared
    type, e.g. ``"control_hz must be a number, got '20' (str)"``. Lists count as tuples (that is how JSON stores
    them); a bool is not a number."""
    hints = typing.get_type_hints(type(obj))
    problems = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        name = prefix + f.name
        tp = hints[f.name]
        if _is_optional_dataclass(tp) and dataclasses.is_dataclass(value):
            problems += type_problems(value, prefix=name + ".")
            continue
        if not _matches(value, tp):
            problems.append(f"{name} must be {_describe(tp)}, got {value!r} ({type(value).__name__})")
    return problems


def timing_problems(control_hz: float, action_scale: float) -> list[str]:
    """Whether a policy acting at ``control_hz`` with ``action_scale`` can be bundled: training jobs call this
    before they train, so a run never ends in a bundle that cannot be saved."""
    problems = []
    lo_hz, hi_hz = CONTROL_HZ_RANGE
    if not (math.isfinite(control_hz) and lo_hz <= control_hz <= hi_hz):
        problems.append(f"control_hz must be in [{lo_hz:g}, {hi_hz:g}] Hz (the rates a hand's control loop can hold), "
                        f"got {control_hz}")
    if not (math.isfinite(action_scale) and 0 < action_scale <= MAX_ACTION_SCALE):
        problems.append(f"action_scale must be in (0, {MAX_ACTION_SCALE}] rad per step, got {action_scale}")
    return problems


def value_problems(cfg: Any) -> list[str]:
    """Range problems of a BundleConfig whose types are right (see the module docstring)."""
    problems = timing_problems(cfg.control_hz, cfg.action_scale)
    if not (math.isfinite(cfg.norm_clip) and cfg.norm_clip > 0):
        problems.append(f"norm_clip must be finite and > 0, got {cfg.norm_clip}")
    if cfg.action_dim != C.NUM_JOINTS:
        problems.append(f"action_dim must be {C.NUM_JOINTS} (one action per joint of the hand), got {cfg.action_dim}")
    problems += _size_problems(cfg)
    problems += joint_limit_problems(cfg.joint_lower, cfg.joint_upper)
    problems += start_shift_problems(cfg)
    return problems


def start_shift_problems(cfg: Any) -> list[str]:
    """A cautious start's shift: finite, one value per latent dimension, and given exactly when start_steps > 0."""
    shift, steps = cfg.start_shift, cfg.start_steps
    if steps < 0:
        return [f"start_steps must be >= 0, got {steps}"]
    if steps == 0:
        return [] if len(shift) == 0 else ["start_shift is given but start_steps is 0: give both or neither"]
    if len(shift) != cfg.latent_dim:
        return [f"start_shift must have one value per latent dimension ({cfg.latent_dim}), got {len(shift)}"]
    if not all(math.isfinite(v) for v in shift):
        return [f"start_shift must be finite, got {list(shift)}"]
    return []


def joint_limit_problems(lower: tuple[float, ...], upper: tuple[float, ...]) -> list[str]:
    """Joint-target limits (16,) rad must be finite, ordered and inside the hand's limits."""
    n = C.NUM_JOINTS
    if len(lower) != n or len(upper) != n:
        return [f"joint_lower/joint_upper must have {n} entries (one per joint), got {len(lower)}/{len(upper)}"]
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    problems = []
    bad = np.flatnonzero(~(np.isfinite(lo) & np.isfinite(hi)))
    if bad.size:
        return [f"joint_lower/joint_upper must be finite; joints {bad.tolist()} are not"]
    inverted = np.flatnonzero(lo >= hi)
    if inverted.size:
        pairs = ", ".join(f"joint {j}: {lo[j]:g} >= {hi[j]:g}" for j in inverted[:4])
        problems.append(f"joint_lower must be < joint_upper at every joint ({pairs}"
                        f"{', ...' if inverted.size > 4 else ''})")
    below = np.flatnonzero(lo < C.JOINT_LOWER - LIMIT_TOLERANCE)
    above = np.flatnonzero(hi > C.JOINT_UPPER + LIMIT_TOLERANCE)
    for side, idx, given, hand in (("joint_lower", below, lo, C.JOINT_LOWER), ("joint_upper", above, hi,
                                                                                C.JOINT_UPPER)):
        if idx.size:
            where = ", ".join(f"joint {j}: {given[j]:g} vs {hand[j]:g}" for j in idx[:4])
            problems.append(f"{side} lies outside the hand's joint limits (envs.constants.JOINT_LOWER/JOINT_UPPER) "
                            f"({where}{', ...' if idx.size > 4 else ''})")
    return problems


def _size_problems(cfg: Any) -> list[str]:
    """Every network size (ints of the shapes, widths, kernels, strides) must be >= 1."""
    fields = {"proprio_shape": cfg.proprio_shape, "actor_hidden": cfg.actor_hidden}
    for net_name in ("encoder", "adaptation"):
        net = getattr(cfg, net_name)
        if net is not None:
            fields.update({f"{net_name}.{f.name}": getattr(net, f.name) for f in dataclasses.fields(net)})
    problems = []
    for name, value in fields.items():
        values = value if isinstance(value, tuple | list) else (value,)
        if any(isinstance(v, int) and v < 1 for v in values):
            problems.append(f"{name} must hold sizes >= 1, got {value!r}")
    return problems


def _is_optional_dataclass(tp: Any) -> bool:
    return any(dataclasses.is_dataclass(a) for a in _union_args(tp))


def _union_args(tp: Any) -> tuple[Any, ...]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return typing.get_args(tp)
    return (tp,)


def _matches(value: Any, tp: Any) -> bool:
    """Whether ``value`` fits the annotation ``tp`` (the subset of types config dataclasses use)."""
    if tp is Any:
        return True
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    if tp is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if tp is str:
        return isinstance(value, str)
    if dataclasses.is_dataclass(tp):
        return isinstance(value, tp)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return value in args
    if origin is tuple:
        if not isinstance(value, tuple | list):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_matches(v, args[0]) for v in value)
        return len(value) == len(args) and all(_matches(v, a) for v, a in zip(value, args, strict=True))
    if origin is dict:
        key_tp, value_tp = args
        return isinstance(value, dict) and all(_matches(k, key_tp) and _matches(v, value_tp)
                                               for k, v in value.items())
    return isinstance(value, origin or tp)


def _describe(tp: Any) -> str:
    """Human words for an annotation: 'a number', 'a list of integers', 'one of 'privileged', 'adaptation''."""
    if tp is Any:
        return "anything"
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in typing.get_args(tp))
    if tp is type(None):
        return "null"
    words = {float: "a number", int: "an integer", str: "a string"}
    if tp in words:
        return words[tp]
    if dataclasses.is_dataclass(tp):
        return f"a {tp.__name__} (a JSON object)"
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        return f"a list of {len(args)} {_plural(args[0])}"
    if origin is dict:
        return f"a JSON object of {_plural(args[1])}"
    return f"a {getattr(tp, '__name__', str(tp))}"


def _plural(tp: Any) -> str:
    plural = {float: "numbers", int: "integers", str: "strings"}
    return plural.get(tp, _describe(tp))
