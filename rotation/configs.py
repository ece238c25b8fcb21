"""Typed config dataclasses -> argparse, with per-field help taken from the field's docstring.

A config is a plain dataclass whose fields carry a docstring on the line after them (the style used across the
project). :func:`add_dataclass_arguments` turns it into argparse options (``field_name`` -> ``--field-name``),
:func:`dataclass_from_args` builds the instance back, and :func:`save_config` writes it as JSON beside a
checkpoint or report.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import math
import os
import sys
import textwrap
import types
import typing
from functools import cache
from pathlib import Path
from typing import Any


@cache
def field_docs(cls: type) -> dict[str, str]:
    """Map field name -> the docstring written right after it in the class body (or its trailing comment)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            source = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = ast.parse(source).body[0].body  # type: ignore[attr-defined]
        lines = source.splitlines()
        for node, nxt in zip(body, [*body[1:], None], strict=True):
            if not isinstance(node, ast.AnnAssign) or not isinstance(node.target, ast.Name):
                continue
            name = node.target.id
            if isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None), ast.Constant):
                docs[name] = " ".join(str(nxt.value.value).split())
            elif "#" in lines[node.lineno - 1]:
                docs[name] = lines[node.lineno - 1].split("#", 1)[1].strip()
    return docs


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def add_dataclass_arguments(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    """Add one option per field of dataclass ``cls``; nested dataclasses become ``--outer.inner-field``."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp, optional = _unwrap_optional(hints[f.name])
        dest = prefix + f.name
        flag = "--" + dest.replace("_", "-")
        default = _field_default(f)
        if dataclasses.is_dataclass(tp):
            add_dataclass_arguments(parser, tp, prefix=dest + ".")
            continue
        kw: dict[str, Any] = dict(dest=dest, default=argparse.SUPPRESS)
        show = "" if default is None and optional else f" (default: {default})"
        help_text = docs.get(f.name, "").replace("%", "%%")  # argparse %-formats help: a literal '%' must be doubled
        show = show.replace("%", "%%")
        origin = typing.get_origin(tp)
        if tp is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, help=help_text + show, **kw)
            continue
        if origin in (tuple, list):
            args = typing.get_args(tp)
            elem = args[0] if args else str
            nargs: Any = "+" if origin is list or (len(args) == 2 and args[1] is Ellipsis) else len(args)
            parser.add_argument(flag, type=_scalar_type(elem), nargs=nargs, help=help_text + show, **kw)
            continue
        if typing.get_origin(tp) is typing.Literal:
            choices = typing.get_args(tp)
            parser.add_argument(flag, type=type(choices[0]), choices=choices, help=help_text + show, **kw)
            continue
        parser.add_argument(flag, type=_scalar_type(tp), help=help_text + show, **kw)


def _finite_float(text: str) -> float:
    """argparse type of float options: a finite number ('nan', 'inf' and text are usage errors, exit status 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def _integer(text: str) -> int:
    """argparse type of int options: a whole number ('1.5', '1e6' and text are usage errors)."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid integer: {text!r}") from None


def _path(text: str) -> Path:
    """argparse type of path options: a non-empty path (an empty one would mean the current directory)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path is not allowed")
    return Path(text)


def _scalar_type(tp: Any) -> Any:
    if tp is float:
        return _finite_float
    if tp is int:
        return _integer
    if tp is Path:
        return _path
    return str


def check_device(name: str, device: str) -> None:
    """``device`` names a torch device that exists here: 'cpu', or 'cuda' / 'cuda:N' with a GPU (never a silent CPU
    fallback)."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"{name}: {device!r} is not a torch device; use 'cpu' or 'cuda' (or 'cuda:N')") from None
    if dev.type == "cpu":
        return
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{name} {device!r}: no CUDA GPU is available to torch here; use --{name} cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{name} {device!r}: there are only {torch.cuda.device_count()} CUDA device(s) "
                             f"(cuda:0 .. cuda:{torch.cuda.device_count() - 1})")
        return
    raise ValueError(f"{name} {device!r}: only 'cpu' and 'cuda' (or 'cuda:N') are supported")


def dataclass_from_args(cls: type, args: argparse.Namespace, prefix: str = "", base: Any = None,
                        **overrides: Any) -> Any:
    """Build ``cls`` from parsed options: fields not given on the command line keep their defaults, those of
    ``base`` when given. A nested config keeps its field's default too (e.g. finetune-adapter's training env), so
    ``--env.randomization.mass 0.1 0.5`` changes the mass range and nothing else of it."""
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    ns = vars(args)
    if base is not None and hasattr(base, "with_hand") and ns.get(prefix + "hand", base.hand) != base.hand:
        base = base.with_hand(ns[prefix + "hand"])  # another hand brings its physics (envs.config.EnvConfig)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp, _ = _unwrap_optional(hints[f.name])
        dest = prefix + f.name
        if dataclasses.is_dataclass(tp):
            if any(k.startswith(dest + ".") for k in ns):
                default = getattr(base, f.name) if base is not None else _field_default(f)
                values[f.name] = dataclass_from_args(tp, args, prefix=dest + ".", base=default)
            continue
        if dest in ns:
            value = ns[dest]
            if typing.get_origin(tp) is tuple and value is not None:
                value = tuple(value)
            values[f.name] = value
    values.update(overrides)
    return cls(**values) if base is None else dataclasses.replace(base, **values)


def _field_default(f: dataclasses.Field) -> Any:
    """A field's default value (a fresh one from its factory), or None without one."""
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return None


def _leaf_fields(cls: type, prefix: str = "") -> dict[str, Any]:
    """Option dest (dotted for nested configs) -> type, for every non-dataclass field of ``cls``."""
    hints = typing.get_type_hints(cls)
    leaves: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp, _ = _unwrap_optional(hints[f.name])
        if dataclasses.is_dataclass(tp):
            leaves.update(_leaf_fields(tp, prefix + f.name + "."))
        else:
            leaves[prefix + f.name] = tp
    return leaves


def _flat_json(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            flat.update(_flat_json(v, f"{prefix}{k}."))
        else:
            flat[prefix + k] = v
    return flat


def inherit_run_options(cls: type, args: argparse.Namespace, run_dir: Path | None,
                        not_inherited: typing.Iterable[str] = ()) -> list[str]:
    """A resume continues the run as it was: every option of ``cls`` the command line does not give takes the value
    in ``run_dir/config.json`` (the run's saved config), so ``--resume`` alone is enough. Options the user gives
    still win (a resume then compares them with the run's and refuses the ones that may not change). Fields in
    ``not_inherited`` (top-level names) keep their defaults. Changes ``args`` in place; returns the inherited dests.

    A missing or unreadable ``config.json`` inherits nothing: the job's own resume check reports it."""
    if run_dir is None:
        return []
    try:
        saved = json.loads((Path(run_dir) / "config.json").read_text())
    except (OSError, ValueError):
        return []
    if not isinstance(saved, dict):
        return []
    leaves = _leaf_fields(cls)
    skip = set(not_inherited)
    ns = vars(args)
    inherited = []
    for dest, value in _flat_json(saved).items():
        if dest not in leaves or dest in ns or dest.split(".")[0] in skip:
            continue  # an option of an older version, one given on the command line, or one a resume must not take
        if leaves[dest] is Path and value is not None:
            value = Path(value)
        ns[dest] = value
        inherited.append(dest)
    return inherited


def config_resuming_in_out(cls: type, args: argparse.Namespace) -> Any:
    """The config of a job whose boolean ``--resume`` continues the run in ``--out`` (train-student,
    finetune-adapter): on a resume, the options the command line leaves out are the run's (:func:`inherit_run_options`).
    """
    if vars(args).get("resume"):
        out = vars(args).get("out", next(f.default for f in dataclasses.fields(cls) if f.name == "out"))
        inherit_run_options(cls, args, Path(out), not_inherited=("out", "resume", "overwrite"))
    return dataclass_from_args(cls, args)


def to_jsonable(obj: Any) -> Any:
    """Dataclasses, paths, tuples and numpy scalars -> plain JSON types."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj


def from_jsonable(cls: type, data: dict[str, Any]) -> Any:
    """Inverse of :func:`to_jsonable` for a (possibly nested) config dataclass; unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown config keys {sorted(unknown)}; expected some of {sorted(names)}")
    values: dict[str, Any] = {}
    for key, value in data.items():
        tp, _ = _unwrap_optional(hints[key])
        if dataclasses.is_dataclass(tp) and isinstance(value, dict):
            value = from_jsonable(tp, value)
        elif typing.get_origin(tp) is tuple and value is not None:
            value = tuple(tuple(v) if isinstance(v, list) else v for v in value)
        elif tp is Path and value is not None:
            value = Path(value)
        values[key] = value
    return cls(**values)


def num_cores() -> int:
    """CPU cores this process may run on (its affinity on Linux): the benchmarks' default thread counts."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def script_main(config_cls: type, run: Any, description: str | None, argv: list[str] | None = None) -> int:
    """Entry point of a script: parse ``config_cls`` from the command line and call ``run(cfg)``. Bad input
    (ValueError, also from the config's own validation) and file-system faults (OSError) end with one line on
    stderr and status 2 or 1, as ``rotate``'s commands do, never a traceback. A ``run`` that returns an int (not a
    bool) returns its exit status (a recipe whose step failed); any other result means status 0."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_dataclass_arguments(parser, config_cls)
    args = parser.parse_args(argv)
    try:
        result = run(dataclass_from_args(config_cls, args))
    except ValueError as err:
        print(f"{parser.prog}: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"{parser.prog}: error: {err}", file=sys.stderr)
        return 1
    return result if isinstance(result, int) and not isinstance(result, bool) else 0


def save_config(cfg: Any, path: str | Path) -> None:
    """Write a config dataclass (or a dict, such as a training run's record) as indented JSON (beside a checkpoint or
    report)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(to_jsonable(cfg), indent=2) + "\n")
