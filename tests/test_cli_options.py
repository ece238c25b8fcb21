"""Every option of every `rotate` subcommand refuses bad values cleanly; a new option is covered the day it is added.

For each subcommand in rotation.cli.COMMANDS whose module has a config dataclass ``Config``, this walks every field
(nested configs included) and tries values that are wrong for the field's type: text or a fraction for an integer;
text, NaN, infinity for a number; and -1, 0 and 1e30 for any number, unless ALLOWED below says why that value is
valid for that field. On the command line (``rotation.cli.main``) a bad value must end with exit status 2 and one
message naming the option, without a traceback; built directly (``dataclasses.replace``), a value of the wrong type
(``"no"`` for a bool, ``"3"`` for an integer) must raise a ValueError naming the field. The job's ``run`` is
replaced by a stub, so nothing is trained or simulated: validation must happen when the config is built.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import types
import typing
from pathlib import Path
from typing import Any

import pytest

from envs.config import EnvConfig
from envs.constants import DEFAULT_HAND
from envs.scene import HANDS
from rotation import cli
from rotation.sim_warp.core import physics_problem

REQUIRED_ARGS: dict[str, list[str]] = {
    # command: arguments it cannot run without (a required option or a positional argument)
    "deploy": ["--hand", "sim-allegro", "--policy", "student"],
    "record": ["--hand", "sim-allegro", "--policy", "student", "--record", "s.h5"],
    "inspect-touch": ["session.h5"],
    "ensemble-adapters": ["--members", "adapter"],
}

ALLOWED: dict[str, dict[str, str]] = {
    # "command:field" (or "*:field" for every command): {kind of value: why it is valid for this field}
    "*:seed": {"zero": "0 is a seed like any other"},
    "*:nthread": {"zero": "0 = one MuJoCo thread per CPU core"},
    "*:workers": {"zero": "0 = load in the main process"},
    "*:num_workers": {"zero": "0 = load in the main process"},
    "probe:token_cache_gb": {"zero": "0 = no token cache: the frozen encoder runs in every step"},
    "touch-report:history": {"zero": "0 = the object's properties from the moment's window alone"},
    "*:node_rank": {"zero": "the first node of a multi-node run is rank 0"},
    "*:ent_coef": {"zero": "no entropy bonus is Hora's setting"},
    "*:log_std_init": {"negative": "a log standard deviation: negative = std below 1", "zero": "std 1 (Hora)"},
    "*:fall_reward": {"negative": "a fall penalty (the default is -20)", "zero": "no penalty; a fall still ends it"},
    "*:pose_diff_reward": {"negative": "a penalty (the default is -0.1)", "zero": "no pose penalty"},
    "*:work_reward": {"negative": "a penalty (the default is -2)", "zero": "no power penalty"},
    "*:noslip_dropout": {"zero": "every episode with the noslip solver"},
    "*:gae_lambda": {"zero": "lambda 0 is one-step TD, a valid estimator"},
    "*:added_mass": {"zero": "no added mass: the nominal object"},
    "*:latent_mix": {"zero": "0 = off: the actor trains on phi alone (the default)"},
    "*:noslip_iterations": {"zero": "0 turns MuJoCo's noslip solver off (the shipped policies' contact model)"},
    "grasps:noise": {"zero": "grasps exactly at the canonical pose"},
    "demos:noise_m": {"zero": "the expert's actions executed as chosen (no DART noise, the default)"},
    "demos:noise_rad": {"zero": "the expert's rotations executed as chosen (the default)"},
    "demos:slip_stop": {"zero": "0 = off: a DAgger round's episode runs on to the env's own end"},
    "demos:beta": {"zero": "0 = the policy drives every step (DAgger's last rounds; the default)"},
    "grasps:hold_seconds": {"zero": "turns the hold check off (the cache records no hold rule)"},
    "train-teacher:critic_warmup": {"zero": "0 = the actor trains from the first update"},
    "finetune-student:critic_warmup": {"zero": "0 = the actor trains from the first update"},
    "deploy:duration": {"zero": "0 runs until Ctrl-C / SIGTERM (documented)"},
    "finetune-adapter:val_fraction": {"zero": "no held-out sessions: train on every session"},
    "ensemble-adapters:touch_every": {"zero": "0 = the first member's refresh period (the default)"},
    "ensemble-adapters:touch_smoothing": {"zero": "0 = each refresh replaces the correction (the default)"},
    "finetune-adapter:action_weight": {"zero": "0 = the latent MSE alone (the default)"},
    "deploy:rt_priority": {"zero": "0 leaves the scheduling alone"},
    "pretrain:unimodal_layers": {"zero": "fusion layers alone (the size's 2 for tinier)"},
    "pretrain:fusion_layers": {"zero": "0 = no fusion: the modalities stay independent"},
    "deploy:grasp": {"zero": "row 0 of the grasp cache"},
    "record:rt_priority": {"zero": "0 leaves the scheduling alone"},
    "record:grasp": {"zero": "row 0 of the grasp cache"},
    "record:duration": {"zero": "0 runs until Ctrl-C / SIGTERM (documented)"},
    "inspect-touch:time": {"negative": "< 0 picks the middle of the session (documented)",
                             "zero": "the start of the session"},
    "demo:deploy_seconds": {"zero": "0 skips the deploy dry run (documented)"},
    "train-student:env.kd": {"zero": "no joint damping is a valid nominal gain"},
    "train-student:env.randomization.scale_jitter": {"zero": "the scale buckets without jitter"},
    "train-student:env.randomization.joint_noise": {"zero": "noise-free joint observations"},
    "train-student:env.randomization.push_prob": {"zero": "no pushes"},
    "train-student:env.randomization.push_scale": {"zero": "pushes of zero force"},
    "train-student:env.randomization.push_decay": {"zero": "a push lasts one policy step"},
    "train-student:env.perturb.added_mass": {"zero": "no added mass"},
    "train-student:env.perturb.com_shift": {"zero": "no shift of the centre of mass"},
    "collect:com_shift": {"zero": "no shift of the centre of mass"},
    "evaluate:com_shift": {"zero": "no shift of the centre of mass"},
    "pretrain:drop_path": {"zero": "no stochastic depth"},
    "pretrain:weight_decay": {"zero": "no weight decay"},
    "train-il:weight_decay": {"zero": "no weight decay"},
    "pretrain:weight_decay_end": {"zero": "no weight decay at the end of the cosine schedule"},
    "pretrain:warmup_fraction": {"zero": "no learning-rate warm-up"},
    "pretrain:teacher_temp_warmup_fraction": {"zero": "the teacher temperature starts at its final value"},
    "pretrain:skin.num_local": {"zero": "no local views: the student sees the global views only"},
    "pretrain:skin.mask_probability": {"zero": "no iBOT masks (the iBOT loss is then 0)"},
    "pretrain:skin.ibot_weight": {"zero": "turns the iBOT loss off"},
    "pretrain:skin.koleo_weight": {"zero": "turns the KoLeo regularizer off"},
    "train-student:env.randomization.com": {"zero": "the range (0, 0): no CoM randomization"},
    "train-student:env.randomization.kd": {"zero": "the range (0, 0): no damping"},
    "finetune-adapter:env.kd": {"zero": "no joint damping is a valid nominal gain"},
    "finetune-adapter:env.randomization.scale_jitter": {"zero": "the scale buckets without jitter"},
    "finetune-adapter:env.randomization.joint_noise": {"zero": "noise-free joint observations"},
    "finetune-adapter:env.randomization.push_prob": {"zero": "no pushes"},
    "finetune-adapter:env.randomization.push_scale": {"zero": "pushes of zero force"},
    "finetune-adapter:env.randomization.push_decay": {"zero": "a push lasts one policy step"},
    "finetune-adapter:env.perturb.added_mass": {"zero": "no added mass"},
    "finetune-adapter:env.perturb.com_shift": {"zero": "no shift of the centre of mass"},
    "finetune-adapter:env.randomization.com": {"zero": "the range (0, 0): no CoM randomization"},
    "finetune-adapter:env.randomization.kd": {"zero": "the range (0, 0): no damping"},
    "finetune-adapter:student_steps": {"zero": "0 = the adapter acts from the first step (no student-only phase)"},
    **{f"{command}:env.randomization.{name}": {"zero": why} for command in ("train-student", "finetune-adapter")
       for name, why in (("joint_friction", "the range (0, 0): frictionless joints"),
                         ("action_delay", "the range (0, 0): targets reach the motors at once"),
                         ("noslip_dropout", "every episode with the noslip solver"))},
    **{f"{command}:env.reward.{term}": {
        "negative": "a penalty weight", "zero": "turns the term off",
        "huge": "reward weights need only be finite (their relative sizes are the reward design)"}
       for command in ("train-student", "finetune-adapter")
       for term in ("rotate", "obj_linvel", "pose_diff", "torque", "work", "tilt", "fall")},
}
"""Values of a 'bad' kind that are valid for one field, each with the reason."""


class _Reached(Exception):
    """The stub ``run`` raises this: the command line was accepted and the config built."""

    def __init__(self, cfg: Any) -> None:
        super().__init__("run reached")
        self.cfg = cfg


def _commands() -> list[str]:
    return [name for name in cli.COMMANDS]


def _module(name: str):
    return importlib.import_module(cli.COMMANDS[name][0])


def _unwrap(tp: Any) -> tuple[Any, bool]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def _fields(cfg: Any, prefix: str = "") -> list[tuple[str, Any, str, Any, bool]]:
    """(dotted name, owning config object, field name, annotated type, optional) of every field, nested included."""
    hints = typing.get_type_hints(type(cfg))
    out = []
    for f in dataclasses.fields(cfg):
        if not f.init:
            continue
        tp, optional = _unwrap(hints[f.name])
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(tp) and dataclasses.is_dataclass(value):
            out += _fields(value, f"{prefix}{f.name}.")
        else:
            out.append((prefix + f.name, cfg, f.name, tp, optional))
    return out


def _allowed(command: str, dotted: str) -> dict[str, str]:
    leaf = dotted.rsplit(".", 1)[-1]
    return {**ALLOWED.get(f"*:{leaf}", {}), **ALLOWED.get(f"{command}:{dotted}", {})}


def _options(command: str) -> dict[str, argparse.Action]:
    """dest -> the argparse action of the subcommand's parser."""
    parser = cli.build_parser(only=command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {a.dest: a for a in sub.choices[command]._actions}


def _run_cli(command: str, argv: list[str], monkeypatch, capsys) -> tuple[int | None, str, Any]:
    """(exit status, stderr, the config if run was reached)."""
    module = _module(command)

    def stub(cfg):
        raise _Reached(cfg)

    monkeypatch.setattr(module, "run", stub)
    try:
        status = cli.main([command, *argv])
    except SystemExit as exit_:
        status = exit_.code if isinstance(exit_.code, int) else 1
    except _Reached as reached:
        return None, capsys.readouterr().err, reached.cfg
    return status, capsys.readouterr().err, None


def _cli_values(tp: Any, nargs: Any) -> dict[str, list[str]]:
    """kind -> command-line words of a bad value for an option of type ``tp``."""
    count = nargs if isinstance(nargs, int) else 1
    elem = tp
    if typing.get_origin(tp) in (tuple, list):
        args = typing.get_args(tp)
        elem = args[0] if args else str
    if elem is int:
        values = {"text": "abc", "fraction": "1.5", "negative": "-1", "zero": "0", "huge": "1" + "0" * 30}
    elif elem is float:
        values = {"text": "abc", "nan": "nan", "inf": "inf", "negative": "-1", "zero": "0", "huge": "1e30"}
    elif typing.get_origin(elem) is typing.Literal:
        values = {"choice": "no-such-choice"}
    else:
        return {}
    return {kind: [word] * count for kind, word in values.items()}


def _wrong_type_values(tp: Any) -> dict[str, Any]:
    """kind -> a value of the wrong type for a field of type ``tp`` (built directly, not parsed)."""
    origin = typing.get_origin(tp)
    if tp is bool:
        return {"text_for_bool": "no", "int_for_bool": 1}
    if tp is int:
        return {"text_for_int": "3", "bool_for_int": True, "float_for_int": 3.0}
    if tp is float:
        return {"text_for_float": "0.5", "bool_for_float": True, "nan": math.nan}
    if tp in (str, Path):
        return {"int_for_text": 3}
    if origin is typing.Literal:
        return {"unknown_choice": "no-such-choice"}
    if origin in (tuple, list):
        args = typing.get_args(tp)
        bad: dict[str, Any] = {"scalar_for_tuple": 7}
        if args and args[0] is float:
            n = 1 if len(args) == 2 and args[1] is Ellipsis else len(args)
            bad["nan_in_tuple"] = (math.nan,) * n
        return bad
    if origin is dict:
        return {"scalar_for_dict": 7}
    return {}


def _names_the_option(message: str, dotted: str) -> bool:
    leaf = dotted.rsplit(".", 1)[-1]
    return any(name in message for name in {leaf, leaf.replace("_", "-"), dotted, dotted.replace("_", "-")})


@pytest.mark.parametrize("command", _commands())
def test_every_option_refuses_bad_values(command, monkeypatch, capsys):
    module = _module(command)
    if not hasattr(module, "Config"):
        pytest.skip(f"{command} has no Config dataclass")
    base_args = REQUIRED_ARGS.get(command, [])
    status, err, base = _run_cli(command, base_args, monkeypatch, capsys)
    assert base is not None, (f"`rotate {command} {' '.join(base_args)}` must be valid (add the arguments it needs "
                              f"to REQUIRED_ARGS): exit {status}, {err}")
    options = _options(command)
    problems = []
    for dotted, owner, name, tp, optional in _fields(base):
        allowed = _allowed(command, dotted)
        action = options.get(dotted)
        if action is not None and action.option_strings:
            for kind, words in _cli_values(tp, action.nargs).items():
                if kind in allowed:
                    continue
                argv = [*base_args, action.option_strings[0], *words]
                status, err, cfg = _run_cli(command, argv, monkeypatch, capsys)
                shown = f"{action.option_strings[0]} {' '.join(words)} ({kind})"
                if cfg is not None:
                    problems.append(f"{shown} was accepted")
                elif status != 2 or "Traceback" in err or not _names_the_option(err, dotted):
                    problems.append(f"{shown}: exit {status}, stderr {err.strip()!r}")
        for kind, value in _wrong_type_values(tp).items():
            if kind in allowed or (optional and value is None):
                continue
            try:
                dataclasses.replace(owner, **{name: value})
            except ValueError as error:
                if not _names_the_option(str(error), dotted):
                    problems.append(f"{dotted}={value!r} ({kind}): the message does not name the field: {error}")
            except Exception as error:  # noqa: BLE001 - any other exception is a traceback for the user
                problems.append(f"{dotted}={value!r} ({kind}): {type(error).__name__} instead of ValueError: {error}")
            else:
                problems.append(f"{dotted}={value!r} ({kind}) was accepted by {type(owner).__name__}")
    assert not problems, f"rotate {command}:\n  " + "\n  ".join(problems)


def test_the_registry_of_exceptions_names_real_fields():
    """Every ALLOWED entry still refers to a field of its command (a renamed option must not keep a stale pass)."""
    known: set[str] = set()
    for command in _commands():
        module = _module(command)
        if not hasattr(module, "Config"):
            continue
        try:
            base = module.Config(**_defaults_needed(command))
        except ValueError:
            continue
        known |= {f"{command}:{dotted}" for dotted, *_ in _fields(base)}
        known |= {f"*:{dotted.rsplit('.', 1)[-1]}" for dotted, *_ in _fields(base)}
    stale = sorted(set(ALLOWED) - known)
    assert not stale, f"ALLOWED names fields that no command has: {stale}"


def _defaults_needed(command: str) -> dict[str, Any]:
    return {"deploy": {"policy": "student"}, "record": {"policy": "student", "record": "s.h5"},
            "inspect-touch": {"session": Path("session.h5")},
            "ensemble-adapters": {"members": ("adapter",)}}.get(command, {})


@pytest.mark.parametrize("command", [c for c in cli.COMMANDS if c not in ("hand-info", "deploy", "record")])
def test_an_output_path_that_is_a_file_is_refused(command, tmp_path, monkeypatch, capsys):
    """--out naming an existing file (for a directory) or a location under a file is refused before any work."""
    options = _options(command)
    if "out" not in options:
        pytest.skip(f"{command} has no --out")
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    status, err, cfg = _run_cli(command, [*REQUIRED_ARGS.get(command, []), "--out", str(blocker / "sub" / "x.png")],
                                monkeypatch, capsys)
    assert cfg is None and status == 2 and "Traceback" not in err, (status, err)
    assert "out" in err and "a_file" in err and "is a file" in err, err


@pytest.mark.parametrize(("argv", "message"), [
    (["train-teacher", "--total-steps", "1e6"], r"argument --total-steps: invalid integer: '1e6'"),
    (["train-teacher", "--learning-rate", "fast"], r"argument --learning-rate: invalid number: 'fast'"),
    (["train-student", "--lr", "nan"], r"argument --lr: 'nan' is not a finite number"),
    (["train-teacher", "--gamma=-inf"], r"argument --gamma: '-inf' is not a finite number"),
    (["grasps", "--scales", "0.8", "inf"], r"argument --scales: 'inf' is not a finite number"),
    (["train-teacher", "--out", ""], r"argument --out: an empty path is not allowed"),
    (["view", "--width", "64.5"], r"argument --width: invalid integer: '64\.5'"),
])
def test_numbers_that_are_not_numbers_are_usage_errors(argv, message, monkeypatch, capsys):
    status, err, cfg = _run_cli(argv[0], argv[1:], monkeypatch, capsys)
    assert cfg is None and status == 2 and "Traceback" not in err
    assert __import__("re").search(message, err), err


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="checks the error on a machine without a GPU")
@pytest.mark.parametrize("command", ["train-teacher", "train-student"])
def test_cuda_without_a_gpu_is_a_usage_error(command, monkeypatch, capsys):
    status, err, cfg = _run_cli(command, ["--device", "cuda"], monkeypatch, capsys)
    assert cfg is None and status == 2, (status, err)
    assert "device 'cuda': no CUDA GPU is available" in err and "Traceback" not in err


def test_a_file_system_fault_is_one_line_and_status_1(monkeypatch, capsys):
    module = _module("grasps")

    def full_disk(cfg):
        raise OSError(28, "No space left on device", "grasps/grasps_cup.npz")

    monkeypatch.setattr(module, "run", full_disk)
    assert cli.main(["grasps"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == ("rotate grasps: error: [Errno 28] No space left on device: 'grasps/grasps_cup.npz'")


@pytest.mark.parametrize("command", list(cli.COMMANDS))
def test_every_help_prints(command, capsys):
    """`rotate COMMAND --help` prints its help and exits 0: a '%' in an option's docstring once made
    `rotate pretrain --help` end in a traceback (argparse %-formats help strings)."""
    with pytest.raises(SystemExit) as exit_info:
        cli.main([command, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: rotate") and "--help" in out


def test_a_nested_option_keeps_the_rest_of_its_config():
    """Giving one field of a nested config changes that field only: the others keep the field's default, here
    finetune-adapter's training env (touch on, the hand's physics widened to slippery and heavy cups), not the
    nested class's own defaults."""
    from adapters.finetune import job as finetune
    from rotation.configs import add_dataclass_arguments, dataclass_from_args

    parser = argparse.ArgumentParser()
    add_dataclass_arguments(parser, finetune.Config)
    default = finetune.Config().env
    cfg = dataclass_from_args(finetune.Config, parser.parse_args(["--env.randomization.mass", "0.1", "0.5"]))
    assert cfg.env.randomization.mass == (0.1, 0.5)
    assert cfg.env.randomization.surface_friction == default.randomization.surface_friction == (0.25, 1.0)
    assert cfg.env.randomization.friction == default.randomization.friction == (0.4, 1.2)
    assert cfg.env.tactile and cfg.env == dataclasses.replace(
        default, randomization=dataclasses.replace(default.randomization, mass=(0.1, 0.5)))
    cfg = dataclass_from_args(finetune.Config, parser.parse_args(["--env.episode-steps", "200"]))
    assert cfg.env.episode_steps == 200 and cfg.env.randomization == default.randomization


CHOICE_NEEDS: dict[str, str] = {
    # "command:--option choice": what else that documented choice needs (its refusal must say so), with the reason
    # the warp backend simulates the first hand model only: on another default hand it asks for that one
    "train-teacher:--backend warp": "cuda" if physics_problem(EnvConfig()) is None else "--hand digit360",
    "collect:--hand xela_v4": "--skin",  # the Xela skin's hand: it is the hand of a skin collection
    "train-student:--backend warp": "cuda",
    "finetune-student:--backend warp": "cuda",
    "evaluate:--backend warp": "cuda",
    "pretrain:--device cuda": "cuda",
    "deploy:--hand allegro": "can",
    "deploy:--hand leap": "ttyUSB0",
    "deploy:--sim-transport slcan": "",
    "collect:--task joystick": "--skin",
    "collect:--shake-grip fingertips": "--task shake",  # only the shaking task holds a bottle
    "collect:--shake-motion strokes": "--task shake",
    # the shipped teacher and student trained on the default hand: the other hands need one of theirs
    **{f"train-student:--env.hand {hand}": "teacher" for hand in HANDS if hand != DEFAULT_HAND},
    **{f"finetune-student:--hand {hand}": "student" for hand in HANDS if hand != DEFAULT_HAND},
    **{f"finetune-adapter:--env.hand {hand}": "tactile" for hand in ("xela", "digit360_v4", "xela_v4")},
}
"""Documented choices that a bare command line cannot take on this machine; the value is a word the one-line
refusal must contain (empty: accepted or refused, either is fine for this option)."""
DOCUMENTED_VALUES: dict[str, list[str]] = {
    # values a --help names in words rather than as argparse choices
    "demo:--adapter-conditions": ["none"],
    "evaluate:--suite": ["perturbations", "nominal"],
}


def _documented_choices(command: str) -> list[tuple[str, str]]:
    """(option string, value) of every choice the subcommand's parser lists, and the ones its help names."""
    out = []
    for action in _options(command).values():
        if not action.option_strings or action.dest == "help":
            continue
        flag = max(action.option_strings, key=len)
        for value in list(action.choices or []) + DOCUMENTED_VALUES.get(f"{command}:{flag}", []):
            out.append((flag, str(value)))
    return out


@pytest.mark.parametrize("command", _commands())
def test_every_documented_choice_is_accepted(command, tmp_path, monkeypatch, capsys):
    """Each value a --help documents (argparse choices, and the values DOCUMENTED_VALUES lists from the help text)
    builds the command's config, or is refused in one line that names what else it needs (CHOICE_NEEDS)."""
    monkeypatch.chdir(tmp_path)
    problems = []
    for flag, value in _documented_choices(command):
        argv = [*REQUIRED_ARGS.get(command, []), flag, value]
        if command in ("deploy", "record") and flag == "--hand":
            argv = [*REQUIRED_ARGS[command][2:], flag, value]
        status, err, cfg = _run_cli(command, argv, monkeypatch, capsys)
        need = CHOICE_NEEDS.get(f"{command}:{flag} {value}")
        if cfg is not None or need == "":
            continue
        if need is not None and need in err.lower() and "Traceback" not in err:
            continue
        problems.append(f"{flag} {value}: status {status}: {err.strip().splitlines()[-1] if err.strip() else ''}")
    assert not problems, f"rotate {command}:\n  " + "\n  ".join(problems)
