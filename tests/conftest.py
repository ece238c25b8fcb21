"""Fixtures shared by the test folders."""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

# headless rendering (the wrist camera, videos) in-process, as `make test` sets it and `rotate` does for its jobs;
# set before any test imports MuJoCo's renderer
os.environ.setdefault("MUJOCO_GL", "egl")

HOW_TO_RUN = {
    "hardware": "need a real hand or sensor attached; run them with `make test-hardware` with the device connected",
    "gpu": "need a CUDA GPU; run them with `make test-gpu` on a machine with one",
}
"""Why the tests of each marker do not run in `make test`, and the command that runs them."""
_deselected: list[pytest.Item] = []


def pytest_deselected(items: list[pytest.Item]) -> None:
    _deselected.extend(items)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked `gpu` are skipped, with the reason and the command, where torch sees no CUDA device."""
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason=f"gpu: these tests {HOW_TO_RUN['gpu']}")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    """Say what was deselected and how to run it, beside pytest's own list of skip reasons (`-rs`)."""
    if not _deselected:
        return
    counts: dict[str, int] = {}
    for item in _deselected:
        marker = next((m for m in HOW_TO_RUN if m in item.keywords), "other")
        counts[marker] = counts.get(marker, 0) + 1
    terminalreporter.write_sep("=", "deselected")
    for marker, n in sorted(counts.items()):
        if marker in HOW_TO_RUN:
            terminalreporter.write_line(f"{n} {marker} test(s) deselected: they {HOW_TO_RUN[marker]}")
        else:
            terminalreporter.write_line(f"{n} test(s) deselected by the command line's -k or -m")

ROOT = Path(__file__).resolve().parents[1]
SCRIPT_DIRS = (ROOT / "scripts", ROOT / "experiments" / "tools")
"""Where load_script looks: the benchmarks and recipes users run, then the experiments' one-off studies."""


@pytest.fixture(scope="session")
def load_script() -> Callable[[str], ModuleType]:
    """``load_script("bench_env")`` imports scripts/bench_env.py (or experiments/tools/NAME.py) as the module
    ``bench_env`` (once)."""

    def load(name: str) -> ModuleType:
        if name not in sys.modules:
            path = next((d / f"{name}.py" for d in SCRIPT_DIRS if (d / f"{name}.py").is_file()), None)
            if path is None:
                raise FileNotFoundError(f"no script {name}.py in {', '.join(str(d) for d in SCRIPT_DIRS)}")
            spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module  # dataclasses look their module up while the class is created
            spec.loader.exec_module(module)
        return sys.modules[name]

    return load


@pytest.fixture(scope="session")
def pressed_and_free_grasp() -> int:
    """Index of the first shipped cup grasp (nominal scale) in which the thumb presses the cup (its Digit 360 reads
    more than 1.5 hPa above rest) and the middle finger touches nothing: found in the cache rather than fixed, so the
    tests that need both kinds of fingertip do not depend on the order of the grasps."""
    from envs.sensors import digit360_model as M
    from envs.sensors.digit360 import FIELD, FINGERS
    from rotation.sim_hardware.hand_physics import HandPhysics

    for grasp in range(100):
        fields = HandPhysics.at_grasp("cup", grasp, hold=True).contact_fields()
        normal = fields[:, FIELD["c0_fn"]] + fields[:, FIELD["c1_fn"]]
        thumb, middle = fields[FINGERS.index("thumb")], fields[FINGERS.index("middle")]
        if (normal[FINGERS.index("thumb")] * M.DEFAULT_MODEL.pressure_per_newton > 1.5 and thumb[FIELD["c0_found"]] == 1
                and middle[FIELD["c0_found"]] == 0 and middle[FIELD["force_n"]] == 0):
            return grasp
    raise AssertionError("no shipped cup grasp has a pressing thumb and a free middle finger")
