"""experiments/tools/grip_lockin.py: the mass the domes feel move with a shaken bottle, per grip."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.grasp_cache import load_default_cache
from envs.shake import ShakeConfig


@pytest.fixture(scope="module")
def lockin(load_script):
    return load_script("grip_lockin")


def test_the_lock_in_reads_the_shake_and_the_fingertip_grip_presses_the_domes_harder(lockin):
    """Seed 10 (rice; 11 g in the fingertip grip's bottle, at most 32 mm in radius): both grips hold the bottle
    through a 1.5 s shake; the felt mass is finite and positive, below a kilogram (the bottle and contents weigh a
    few tens of grams, the fingers' springs add more), and the fingertip grip's domes press several times as hard
    as the palm grip's (measured over seeds 10-89: 6.3 N against 1.6 N)."""
    grasps = load_default_cache("cup", "", "digit360_v4")
    out, masses = {}, {}
    for grip in ("fingertips", "palm"):
        ep, mass, felt, held, normal = lockin.felt_mass(ShakeConfig(duration_s=1.5, grip=grip), 10, grasps)
        assert held and math.isfinite(felt) and 0.0 < felt < 1.0, (grip, felt)
        assert ep.content == "rice"
        out[grip], masses[grip] = normal, mass
    assert masses["fingertips"] == pytest.approx(0.011, abs=0.002) and masses["palm"] >= masses["fingertips"]
    assert out["fingertips"] > 2 * out["palm"] and np.isfinite(list(out.values())).all(), out
