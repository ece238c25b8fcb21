"""Checks shared by every config: values of the annotated types, numbers in range, seeds, output paths.

Each check raises a ValueError naming the field and what is allowed; nothing is clamped or converted silently.
Configs call them from ``__post_init__`` so that a bad value is refused on construction, before any work.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import types
import typing
from functools import cache
from pathlib import Path
from typing import Any

MAX_SEED = 2**64 - 1
"""Seeds are 64-bit keys (envs.rng): 0 .. 2**64 - 1, gymnasium's rule (non-negative integers) with a ceiling."""


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) is typing.Literal:
        return "one of " + ", ".join(repr(c) for c in typing.get_args(tp))
    if tp is type(None):
        return "None"
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        plural = {float: "numbers", int: "integers", str: "strings", Path: "paths", bool: "booleans"}
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a tuple of {plural.get(args[0], _type_name(args[0]))}"
        if len(set(args)) == 1 and args[0] in plural:
            return f"a tuple of {len(args)} {plural[args[0]]}"
        return f"a tuple of {len(args)} values ({', '.join(_type_name(a) for a in args)})"
    if origin is dict:
        k, v = typing.get_args(tp)
        return f"a dict of {_type_name(k)} -> {_type_name(v)}"
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "True or False"
    if tp is str:
        return "a string"
    if tp is Path:
        return "a path"
    return "a " + getattr(tp, "__name__", str(tp))


def _matches(value: Any, tp: Any) -> bool:
    """Whether ``value`` is a value of annotation ``tp`` (any real number for a float; ranges are checked apart)."""
    if tp is Any:
        return True
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in typing.get_args(tp))
    if origin is typing.Literal:
        return any(value == c and type(value) is type(c) for c in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool) or type(value).__name__ == "bool_"  # numpy's bool too
    if tp is int:
        return _is_int(value)
    if tp is float:
        return _is_real(value)
    if tp is str:
        return isinstance(value, str)
    if tp is Path:
        return isinstance(value, str | os.PathLike)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, tuple | list):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_matches(v, args[0]) for v in value)
        return len(value) == len(args) and all(_matches(v, a) for v, a in zip(value, args, strict=True))
    if origin is list:
        (arg,) = typing.get_args(tp)
        return isinstance(value, list | tuple) and all(_matches(v, arg) for v in value)
    if origin is dict:
        k, v = typing.get_args(tp)
        return isinstance(value, dict) and all(_matches(a, k) and _matches(b, v) for a, b in value.items())
    if isinstance(tp, type):
        return isinstance(value, tp)
    return True  # an annotation this checker does not know: left to the config's own checks


def check_types(cfg: Any, prefix: str = "", skip: tuple[str, ...] = ()) -> None:
    """Every field of dataclass ``cfg`` (but those in ``skip``, which the config checks itself) holds a value of its
    annotated type.

    ``True`` is not an integer, ``"no"`` is not a bool and ``1.0`` is not an int here: a value of the wrong type is
    refused, not interpreted. Ranges (finite, positive, ...) are each config's own checks.
    """
    hints = _hints(type(cfg))
    for f in dataclasses.fields(cfg):
        if f.name in skip:
            continue
        value = getattr(cfg, f.name)
        tp = hints[f.name]
        if not _matches(value, tp):
            raise ValueError(f"{prefix}{f.name} must be {_type_name(tp)}, got {type(value).__name__} {value!r}")


def check_finite(cfg: Any, names: tuple[str, ...], prefix: str = "") -> None:
    """The float fields ``names`` of ``cfg`` are finite (any sign)."""
    for name in names:
        value = getattr(cfg, name)
        if not (_is_real(value) and math.isfinite(float(value))):
            raise ValueError(f"{prefix}{name} must be a finite number, got {value!r}")


def check_number(name: str, value: float, low: float | None = None, high: float | None = None, *,
                 low_open: bool = False, high_open: bool = False, unit: str = "") -> None:
    """``value`` is a finite number within [low, high] (an open end with ``low_open`` / ``high_open``)."""
    lo = "-inf" if low is None else f"{low:g}"
    hi = "inf" if high is None else f"{high:g}"
    allowed = f"{'(' if low_open or low is None else '['}{lo}, {hi}{')' if high_open or high is None else ']'}"
    allowed += f" {unit}" if unit else ""
    ok = _is_real(value) and math.isfinite(float(value))
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        raise ValueError(f"{name} must be a finite number in {allowed}, got {value!r}")


def check_int(name: str, value: int, low: int | None = None, high: int | None = None, unit: str = "") -> None:
    """``value`` is an integer (not a bool) within [low, high]."""
    if not _is_int(value) or (low is not None and value < low) or (high is not None and value > high):
        lo = "-inf" if low is None else str(low)
        hi = "inf" if high is None else str(high)
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}]{' ' + unit if unit else ''}, got {value!r}")


def check_seed(name: str, seed: Any) -> int:
    """A seed is an integer in [0, 2**64 - 1] (gymnasium refuses negative seeds; the env's keys are 64-bit)."""
    check_int(name, seed, 0, MAX_SEED)
    return int(seed)


def check_output_dir(name: str, path: str | os.PathLike) -> None:
    """``path`` is a directory, or can be created: no file in its place, and its nearest existing parent writable."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{name} {str(p)!r} is a file, not a directory; give a directory to write to")
    _check_writable_parent(name, p, p)


def check_output_file(name: str, path: str | os.PathLike) -> None:
    """``path`` can be written as a file: not a directory, and its nearest existing parent is a writable directory."""
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{name} {str(p)!r} is a directory; give a file name")
    if p.exists() and not os.access(p, os.W_OK):
        raise ValueError(f"{name} {str(p)!r} is not writable")
    _check_writable_parent(name, p, p.parent)


def _check_writable_parent(name: str, p: Path, start: Path) -> None:
    """The nearest existing directory at or above ``start`` (where ``p`` will be created) is a writable directory."""
    existing = start
    while not existing.exists():
        if existing.parent == existing:
            break
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        raise ValueError(f"{name} {str(p)!r} cannot be created: {str(existing)!r} is a file")
    if existing.exists() and not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{name} {str(p)!r} cannot be written: no write permission in {str(existing)!r}")


def check_optional_file(name: str, path: str | os.PathLike, hint: str = "") -> None:
    """``path`` is empty (meaning: the default) or an existing file."""
    if str(path) and not Path(path).is_file():
        what = "a directory, not a file" if Path(path).is_dir() else "no such file"
        raise ValueError(f"{name}: {what}: {str(path)!r}{'; ' + hint if hint else ''}")
