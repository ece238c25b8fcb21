"""experiments/tools/load_share.py: the contact forces on the object by source (fingertip domes, rest of the hand,
floor)."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

SUPPORTS = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <geom name="dome" type="sphere" size="0.02" pos="-0.05 0 0.1"/>
    <geom name="pad" type="box" size="0.02 0.02 0.02" pos="0.05 0 0.1"/>
    <body name="object" pos="0 0 0.146">
      <freejoint/>
      <geom type="box" size="0.1 0.05 0.005" mass="0.5"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def load_share(load_script):
    return load_script("load_share")


def test_a_slab_resting_on_a_dome_and_a_pad_splits_its_weight_between_them(load_share):
    m = mujoco.MjModel.from_xml_string(SUPPORTS)
    d = mujoco.MjData(m)
    for _ in range(500):  # settle
        mujoco.mj_step(m, d)
    ids = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("floor", "dome", "pad")}
    obj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
    f = load_share.object_forces(m, d, obj, {ids["dome"]}, ids["floor"])
    weight = 0.5 * 9.81
    assert f["domes"][2] + f["hand"][2] == pytest.approx(weight, rel=0.02)  # at rest: the supports carry it all
    assert f["domes"][2] > 0.3 * weight and f["hand"][2] > 0.3 * weight  # both supports, half each by symmetry
    assert np.allclose(f["floor"], 0.0)  # the slab does not reach the floor
    assert float(f["dome_normal"]) == pytest.approx(np.linalg.norm(f["domes"]), rel=0.02)  # pressed straight down
    assert float(f["dome_tangential"]) < 0.02 * weight

    # the same slab on the floor: the floor carries it, and nothing touches a dome
    d2 = mujoco.MjData(m)
    d2.qpos[2] = 0.005
    for _ in range(200):
        mujoco.mj_step(m, d2)
    f2 = load_share.object_forces(m, d2, obj, {ids["dome"]}, ids["floor"])
    assert f2["floor"][2] == pytest.approx(weight, rel=0.02)
    assert np.allclose(f2["domes"], 0.0) and float(f2["dome_normal"]) == 0.0


def test_a_short_run_measures_every_condition_on_the_same_episodes(load_share, capsys):
    assert load_share.main(["--policy", "student", "--envs", "2", "--steps", "4", "--warmup", "1"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["policy"] == "student" and out["envs"] == 2
    nominal, heavy, slippery = out["nominal"], out["mass_+0.2kg"], out["friction_0.25"]
    assert nominal["samples"] == heavy["samples"] == 2 * 3  # two episodes, steps 1-3 counted
    assert slippery["episodes_to_the_end"] == 1 and 3 <= slippery["samples"] < 6  # one slippery cup falls at once
    for r in (nominal, heavy, slippery):
        assert r["hand_share"] == pytest.approx(r["hand_z"] / r["weight"], abs=1e-3)
        assert r["floor_z"] == 0.0  # held cups
        assert r["dome_normal"] > 0.0  # the grasp presses the cup
    assert len(nominal["episode_ratio"]) == 2 and nominal["ratio_separation"] == 0.0
    assert all(0.0 < r < 10.0 for r in heavy["episode_ratio"] + slippery["episode_ratio"])
    assert heavy["weight"] - nominal["weight"] == pytest.approx(0.2 * 9.81, abs=1e-3)  # the same cups, +0.2 kg
    assert 0.0 < slippery["weight"] < nominal["weight"] + 0.2 * 9.81  # the m g of the cup still held, then both


def test_separation_is_the_shift_of_the_mean_in_nominal_standard_deviations(load_share):
    assert load_share.separation([3.0, 3.0], [1.0, 2.0, 3.0]) == 1.0
    assert load_share.separation([0.5], [1.0, 2.0, 3.0]) == -1.5
    assert load_share.separation([3.0], [1.0]) is None and load_share.separation([], [1.0, 2.0]) is None


def test_bad_settings_are_one_line_errors(load_share, capsys):
    assert load_share.main(["--warmup", "10", "--steps", "10"]) == 2
    assert load_share.main(["--added-mass", "0.4"]) == 2
    assert load_share.main(["--policy", "adapter"]) == 2
    err = capsys.readouterr().err
    assert "--warmup must be" in err and "--added-mass must be" in err and "a tactile adapter" in err
    assert "Traceback" not in err
