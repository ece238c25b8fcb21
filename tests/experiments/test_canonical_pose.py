"""experiments/tools/canonical_pose.py: the sampling IK places the domes around the cup and reports what it found."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from envs import constants as C

TOOL = Path(__file__).resolve().parents[2] / "experiments" / "tools" / "canonical_pose.py"


@pytest.fixture(scope="module")
def tool(load_script):
    return load_script("canonical_pose")


def test_the_search_brings_every_dome_closer_than_the_middle_pose(tool, tmp_path):
    """Run as a user runs it (a fresh process, so MUJOCO_GL applies to its picture)."""
    out = tmp_path / "cp"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, str(TOOL), "--out", str(out), "--centres-x", "0.04", "--centres-z", "0.06",
                           "--samples", "300", "--seed", "3"], env=env, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads((out / "canonical_pose.json").read_text())
    assert json.loads(done.stdout.strip().splitlines()[-1])["best"] == report["best"]
    assert (out / "canonical_pose.png").stat().st_size > 1000
    cfg = tool.Config()
    hand = tool.Hand()
    centre = np.array([0.04, 0.0, 0.06])
    goal = tool.targets(centre, 0.040 * cfg.scale + hand.radius, cfg.spread)
    middle = (C.JOINT_LOWER + C.JOINT_UPPER) / 2
    before = sum(hand.cost(middle, f, goal[f], centre, cfg.facing_weight) for f in range(4))
    assert report["best"]["cost"] < before / 3
    pose = np.asarray(report["best"]["pose"])
    assert np.all(pose >= C.JOINT_LOWER - 1e-9) and np.all(pose <= C.JOINT_UPPER + 1e-9)
