"""experiments/tools/load_share.py: the contact forces on the object by source (fingertip domes, rest of the hand,
floor)."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

from envs.config import MAX_OBJECT_MASS, Perturbation, default_randomization
from rotation.bundles import load_bundle, policy_hand
from rotation.evaluate.suites import condition_name

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


def heavy_mass(policy: str) -> float:
    """The added mass of the heavy condition on ``policy``'s hand (the script runs it there): 0.2 kg where the hand's
    randomization leaves room for it (the first hand's 0.25 kg cups), else what it leaves (0.1 kg on the 0.4 kg
    mugs of 'digit360_v4')."""
    hand = policy_hand(load_bundle(policy))
    return round(min(0.2, MAX_OBJECT_MASS - default_randomization(hand).mass[1]), 3)


def test_a_short_run_measures_every_condition_on_the_same_episodes(load_share, capsys):
    added = heavy_mass("student")
    assert added > 0
    assert load_share.main(["--policy", "student", "--envs", "2", "--steps", "4", "--warmup", "1",
                            "--added-mass", str(added)]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["policy"] == "student" and out["envs"] == 2
    nominal, heavy = out["nominal"], out[condition_name(Perturbation(added_mass=added))]
    slippery = out[condition_name(Perturbation(friction_scale=0.25))]
    assert nominal["samples"] == heavy["samples"] == 2 * 3  # two episodes, steps 1-3 counted
    for r in (nominal, heavy, slippery):
        # an episode counts its steps after the warm-up until it ends: all 3 if it reaches the end, fewer if not
        assert 3 * r["episodes_to_the_end"] <= r["samples"] <= 2 * 3
        assert (r["samples"] == 2 * 3) == (r["episodes_to_the_end"] == 2)
        assert r["hand_share"] == pytest.approx(r["hand_z"] / r["weight"], abs=1e-3)
        assert r["floor_z"] == 0.0  # held cups
        assert r["dome_normal"] > 0.0  # the grasp presses the cup
    assert len(nominal["episode_ratio"]) == 2 and nominal["ratio_separation"] == 0.0
    assert all(0.0 < r < 10.0 for r in heavy["episode_ratio"] + slippery["episode_ratio"])
    assert heavy["weight"] - nominal["weight"] == pytest.approx(added * 9.81, abs=1e-3)  # the same cups, heavier
    if slippery["samples"] == nominal["samples"]:  # the same cups, every one still held: the same m g
        assert slippery["weight"] == pytest.approx(nominal["weight"], abs=1e-3)
    assert 0.0 < slippery["weight"] < nominal["weight"] + added * 9.81  # the m g of the cups still held


def test_separation_is_the_shift_of_the_mean_in_nominal_standard_deviations(load_share):
    assert load_share.separation([3.0, 3.0], [1.0, 2.0, 3.0]) == 1.0
    assert load_share.separation([0.5], [1.0, 2.0, 3.0]) == -1.5
    assert load_share.separation([3.0], [1.0]) is None and load_share.separation([], [1.0, 2.0]) is None


def test_bad_settings_are_one_line_errors(load_share, capsys, tmp_path):
    from adapters.bundle import build_adapted

    adapter = tmp_path / "adapter"  # no adapter ships: a fresh one on the shipped student
    build_adapted("student", "sparshx-tinier-sim", ("pressure",), touch_every=4).save(adapter)
    assert load_share.main(["--warmup", "10", "--steps", "10"]) == 2
    assert load_share.main(["--added-mass", "0.4"]) == 2
    assert load_share.main(["--policy", str(adapter)]) == 2
    err = capsys.readouterr().err
    assert "--warmup must be" in err and "--added-mass must be" in err and "a tactile adapter" in err
    assert "Traceback" not in err
