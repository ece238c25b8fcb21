"""What the CPU recipes of scripts/ share: running their steps in order (each a `rotate` command, or a Python script
given as ``["python", path, ...]``), stopping at the first that fails, and whether a pretraining run is done."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path


def progress_args(progress: bool) -> list[str]:
    """The option a recipe passes to each `rotate` step for its own --progress / --no-progress."""
    return [] if progress else ["--no-progress"]


def pretrained(run: Path, steps: int) -> bool:
    """Whether the `rotate pretrain` run ``run`` holds its checkpoint of step ``steps`` (or later)."""
    ckpts = sorted(Path(run).glob("ckpt_*.safetensors"))
    try:
        return bool(ckpts) and int(ckpts[-1].stem.split("_")[1]) >= steps
    except (IndexError, ValueError):
        return False


def report_complete(folder: Path) -> bool:
    """Whether ``folder`` holds a finished report: results.json without ``"complete": false`` (a stopped
    `rotate probe` writes one after every variant and budget, and the same command continues it)."""
    try:
        return json.loads((Path(folder) / "results.json").read_text()).get("complete", True) is not False
    except (OSError, ValueError, AttributeError):
        return False


def run_steps(name: str, todo: list[tuple[str, list[str]]], dry_run: bool) -> int:
    """Print and (unless ``dry_run``) run each (what, command) of ``todo``; the first non-zero status stops the
    recipe and is returned (the recipe continues from there when run again)."""
    from rotation import cli

    for what, args in todo:
        shown = shlex.join(args) if args[0] == "python" else f"rotate {shlex.join(args)}"
        print(f"{name}: {what}\n  {shown}", flush=True)
        if dry_run:
            continue
        status = subprocess.call([sys.executable, *args[1:]]) if args[0] == "python" else cli.main(args)
        if status != 0:
            print(f"{name}: stopped ({what} ended with status {status}); run the script again to continue",
                  file=sys.stderr)
            return status
    return 0
