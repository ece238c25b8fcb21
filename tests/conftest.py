"""Fixtures shared by the test folders."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture(scope="session")
def load_script() -> Callable[[str], ModuleType]:
    """``load_script("spin_stats")`` imports scripts/spin_stats.py as the module ``spin_stats`` (once)."""

    def load(name: str) -> ModuleType:
        if name not in sys.modules:
            spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
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
    from envs.sensors import digit360_render as R
    from envs.sensors.digit360 import FIELD, FINGERS
    from rotation.sim_hardware.hand_physics import HandPhysics

    for grasp in range(100):
        fields = HandPhysics.at_grasp("cup", grasp, hold=True).contact_fields()
        normal = fields[:, FIELD["c0_fn"]] + fields[:, FIELD["c1_fn"]]
        thumb, middle = fields[FINGERS.index("thumb")], fields[FINGERS.index("middle")]
        if (normal[FINGERS.index("thumb")] * R.DEFAULT_MODEL.pressure_per_newton > 1.5 and thumb[FIELD["c0_found"]] == 1
                and middle[FIELD["c0_found"]] == 0 and middle[FIELD["force_n"]] == 0):
            return grasp
    raise AssertionError("no shipped cup grasp has a pressing thumb and a free middle finger")
