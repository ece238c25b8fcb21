"""The ``rotate`` command: one subcommand per job of the workflow.

Each subcommand lives in a module that exposes a config dataclass ``Config`` (one docstring per field, which
becomes the option's help) and ``run(cfg)``; modules with options that do not fit a dataclass field also define
``add_arguments(parser)`` and ``config_from_args(args)``. The module docstring is the subcommand's description.
Modules are imported only when their subcommand runs, so ``rotate --help`` stays fast.

Exit statuses: 0 done; 2 a bad option (one line naming it); 1 a request that cannot be done as asked or a job that
failed (envs.errors: one line saying what, why and what to try), or a file-system or device fault; 130 / 143 after
Ctrl-C / SIGTERM. ``--debug`` anywhere on the command line (or ROTATE_DEBUG=1) shows the traceback of any of these
instead, for bug reports; an exception of any other kind is a bug and always shows its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from envs.errors import JobFailed, RequestRefused
from rotation.configs import add_dataclass_arguments, dataclass_from_args

COMMANDS: dict[str, tuple[str, str]] = {
    # name: (module, one-line summary)
    "grasps": ("rotation.jobs.grasps", "generate the initial-grasp cache for objects and scales"),
    "view": ("rotation.jobs.view", "render an object/grasp (PNG) or a rollout (MP4) headless"),
    "train-teacher": ("rotation.train.teacher", "train the privileged teacher with PPO on the batched env"),
    "train-student": ("rotation.train.student", "distill the proprioceptive student from a frozen teacher"),
    "finetune-student": ("rotation.train.finetune_student",
                         "fine-tune a distilled student's actor with PPO on its own latent estimate"),
    "evaluate": ("rotation.evaluate.job", "compare policies under friction, mass and CoM perturbations"),
    "demo": ("rotation.jobs.demo", "the end-to-end demo on the shipped defaults"),
    "hand-info": ("rotation.jobs.hand_info", "print a hand's firmware, serial, temperatures and joint positions"),
    "collect": ("rotation.jobs.collect", "record simulated touch sessions (Digit 360 on) with a policy"),
    "demos": ("rotation.jobs.demos", "record a scripted expert's demonstrations of a task (plug insertion)"),
    "inspect-touch": ("rotation.jobs.inspect_tactile", "plot the four touch streams of a session window (PNG)"),
    "deploy": ("rotation.deploy.job", "run a policy on a real or emulated hand with safety limits and recording"),
    "record": ("rotation.jobs.record", "record a labelled session (the object's measured properties) for adapter "
               "fine-tuning"),
    "touch-info": ("rotation.jobs.touch_info",
                   "list the attached Digit 360 sensors, or read one and report each stream"),
    "rehearse": ("rotation.jobs.rehearse", "rehearse the lab workflow (record, fine-tune, deploy) on emulated hardware "
                 "with faults"),
    "encoder-info": ("rotation.tactile.encoder_info", "describe a touch encoder; check that a checkpoint loads"),
    "cache-touch": ("rotation.data.window_cache", "pre-render touch windows of sessions into shards for fast training"),
    "pretrain": ("rotation.tactile.pretrain.job", "pretrain a touch encoder by self-distillation (DINO, EMA teacher)"),
    "probe": ("rotation.tactile.probes.job", "probe frozen vs end-to-end touch encoders at several label budgets"),
    "touch-report": ("rotation.tactile.ladder.job",
                     "how much friction, mass, force and slip each stage of the touch path still holds"),
    "finetune-adapter": ("adapters.finetune.job", "fine-tune the tactile adapter toward the teacher's latent"),
    "train-il": ("rotation.il.job", "train an imitation policy (action chunks) on demonstrations (plug insertion)"),
    "ensemble-adapters": ("adapters.ensemble_job", "combine tactile adapters of one student into one policy"),
}
"""Subcommand registry; later issues add their jobs here."""
RENAMED = {"inspect-tactile": "inspect-touch"}
"""Earlier command names that still work (old name -> the command)."""


def _load(name: str):
    module_name, _ = COMMANDS[name]
    return importlib.import_module(module_name)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rotate",
        description="Tactile in-hand rotation: simulate, train, evaluate and deploy on an Allegro or LEAP hand.",
        epilog="Exit status: 0 done, 1 the request cannot be done or the job failed, 2 a bad option, 130 / 143 "
               "Ctrl-C / SIGTERM. Add --debug (or set ROTATE_DEBUG=1) to see the traceback behind an error line.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, summary) in COMMANDS.items():
        if only is not None and name != only:
            sub.add_parser(name, help=summary)
            continue
        module = _load(name)
        p = sub.add_parser(
            name, help=summary, description=module.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
        )
        if hasattr(module, "add_arguments"):
            module.add_arguments(p)
        else:
            add_dataclass_arguments(p, module.Config)
    return parser


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


def _expected_error(err: Exception) -> tuple[str, int]:
    """(the word before the message, exit status) of an error a job expects."""
    if isinstance(err, RequestRefused):
        return "refused", 1  # well formed but impossible
    if isinstance(err, JobFailed):
        return "failed", 1
    if isinstance(err, OSError):
        return "error", 1  # a fault of the file system or a device (disk full, permission, a vanished path)
    return "error", 2  # any other ValueError: a bad option


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("ROTATE_DEBUG", "") not in ("", "0")
    argv = [a for a in argv if a != "--debug"]
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in RENAMED:
        argv[argv.index(command)] = command = RENAMED[command]
    if command is not None and command not in COMMANDS:
        print(f"rotate: unknown command {command!r}; choose one of: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    parser = build_parser(only=command)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    module = _load(args.command)
    try:
        # a config validates itself on construction: its ValueError is bad input too
        if hasattr(module, "config_from_args"):
            cfg = module.config_from_args(args)
        else:
            cfg = dataclass_from_args(module.Config, args)
        result = module.run(cfg)
    except KeyboardInterrupt as err:
        # 130 for Ctrl-C, 143 for SIGTERM (rotation.interrupt.Interrupted, raised after the job saved its outputs)
        code = getattr(err, "exit_code", 130)
        print(f"rotate {args.command}: {err or 'interrupted'} (exit status {code})", file=sys.stderr)
        return code
    except (ValueError, OSError, JobFailed) as err:
        # the errors a job expects (envs.errors, a bad option, a file-system or device fault): one line
        if debug:
            raise
        kind, code = _expected_error(err)
        print(f"rotate {args.command}: {kind}: {_one_line(err)}", file=sys.stderr)
        return code
    # a job that ends itself cleanly on a fault or a signal (deploy) reports its exit status in its result
    if isinstance(result, dict) and isinstance(result.get("exit_code"), int):
        return result["exit_code"]
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
