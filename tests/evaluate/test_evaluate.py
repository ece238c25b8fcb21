"""`rotate evaluate` on a tiny budget: random-init bundles, short episodes, a well-formed report."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch

from envs.config import ContactConfig, Perturbation
from envs.grasps import generate_grasps
from envs.metrics import METRICS
from envs.sim_identity import LEGACY_HAND
from rotation.evaluate import job
from rotation.evaluate.report import EPISODE_FIELDS
from rotation.evaluate.suites import get_suite, make_condition
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Random-init teacher and student bundles and a small grasp cache; the bundles record no sim, so they act on
    LEGACY_HAND, the hand the cache is generated for."""
    root = tmp_path_factory.mktemp("evaluate")
    torch.manual_seed(0)
    teacher = PolicyBundle(BundleConfig())
    teacher.save(root / "teacher")
    teacher.to_student().save(root / "student")
    generate_grasps("cup", (0.78,), per_scale=4, batch_size=16, max_rounds=5, seed=0, nthread=1,
                    hand=LEGACY_HAND).save(root / "grasps.npz")
    return root


def make_cfg(root: Path, out: Path, **kw) -> job.Config:
    base = dict(policies={"teacher": str(root / "teacher"), "student": str(root / "student")}, episodes=2,
                episode_steps=12, grasp_cache=str(root / "grasps.npz"), out=out, num_envs=2, nthread=1,
                progress=False)
    return job.Config(**{**base, **kw})


def test_suite_report_is_well_formed(setup, tmp_path):
    conds = ("nominal", "friction_0.5", "mass_+0.1kg", "friction_0.5+mass_+0.1kg")
    rows = job.run(make_cfg(setup, tmp_path / "eval", suite="perturbations", conditions=conds))
    result = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert result["rows"] == rows
    assert result["config"]["episodes"] == 2
    assert [(r["policy"], r["condition"]) for r in rows] == [(p, c) for c in conds for p in ("teacher", "student")]
    for r in rows:
        assert r["episodes"] == 2
        assert {"friction_scale", "added_mass", "com_shift", *METRICS} <= set(r)
        assert all(np.isfinite(r[m]) for m in METRICS)
        assert 0.0 < r["ttf"] <= 1.0 and r["torque"] > 0 and r["lin_vel"] >= 0 and r["vertical_drift"] >= 0
        per = r["per_episode"]  # each episode's values, in episode order: the means and the net rate follow
        assert set(per) == set(EPISODE_FIELDS) and all(len(v) == 2 for v in per.values())
        assert np.mean(per["ttf"]) == pytest.approx(r["ttf"], abs=1e-5)
        assert sum(per["rotation_total"]) / sum(per["in_hand_time"]) == pytest.approx(r["net_rotation_rate"],
                                                                                     abs=1e-4)
    by_cond = {r["condition"]: r for r in rows if r["policy"] == "teacher"}
    assert by_cond["friction_0.5+mass_+0.1kg"]["friction_scale"] == 0.5
    assert by_cond["friction_0.5+mass_+0.1kg"]["added_mass"] == 0.1
    md = (tmp_path / "eval" / "results.md").read_text()
    assert md.count("| teacher |") == 4 and "rotation_rate (rad/s)" in md
    assert sorted(p.stem for p in (tmp_path / "eval" / "plots").glob("*.png")) == sorted([*METRICS, "bars"])
    assert json.loads((tmp_path / "eval" / "config.json").read_text())["suite"] == "perturbations"


def test_same_seeds_for_every_policy(setup, tmp_path):
    # one bundle under two labels must score identically: both met the same episodes; and a rerun is bit-identical
    same = {"a": str(setup / "teacher"), "b": str(setup / "teacher")}
    rows = job.run(make_cfg(setup, tmp_path / "a", policies=same, episodes=3, friction_scale=0.5))
    assert [r["condition"] for r in rows] == ["friction_0.5", "friction_0.5"]
    assert {**rows[0], "policy": "b"} == rows[1]
    assert job.run(make_cfg(setup, tmp_path / "b", policies=same, episodes=3, friction_scale=0.5)) == rows


def test_conditions():
    assert job.resolve_conditions(job.Config()) == [make_condition(Perturbation())]
    custom = job.resolve_conditions(job.Config(added_mass=0.1, com_shift=(0.0, 0.01, 0.0)))
    assert [c.name for c in custom] == ["mass_+0.1kg+com_0_0.01_0"] and custom[0].axis == "combined"
    suite = get_suite("perturbations")
    names = [c.name for c in suite]
    assert names[0] == "nominal" and len(set(names)) == len(names)
    assert {c.axis for c in suite} == {"nominal", "friction", "mass", "com", "combined"}


def test_bad_input(setup, tmp_path):
    with pytest.raises(ValueError, match="no bundle directory at 'nobody'.*shipped bundles"):
        job.run(make_cfg(setup, tmp_path / "x", policies={"x": "nobody"}))
    with pytest.raises(ValueError, match=r"unknown condition\(s\) \['icy'\].*friction_0.5"):
        job.run(make_cfg(setup, tmp_path / "x", suite="perturbations", conditions=("icy",)))
    with pytest.raises(ValueError, match="unknown suite 'windy'; choose one of: perturbations"):
        job.run(make_cfg(setup, tmp_path / "x", suite="windy"))
    with pytest.raises(ValueError, match="either a suite or perturbation values"):
        job.run(make_cfg(setup, tmp_path / "x", suite="perturbations", friction_scale=0.5))
    with pytest.raises(ValueError, match="friction_scale must be finite and > 0"):
        job.run(make_cfg(setup, tmp_path / "x", friction_scale=-1.0))


def test_cli_with_video(setup, tmp_path):
    """The `rotate evaluate` command end to end, in a fresh process so MUJOCO_GL applies (headless EGL)."""
    out = tmp_path / "cli"
    cmd = [sys.executable, "-m", "rotation.cli", "evaluate", "--policy", f"student={setup / 'student'}",
           "--added-mass", "0.05", "--episodes", "1", "--episode-steps", "6", "--num-envs", "1",
           "--grasp-cache", str(setup / "grasps.npz"), "--out", str(out), "--video", "--no-progress"]
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [(r["policy"], r["condition"], r["added_mass"]) for r in rows] == [("student", "mass_+0.05kg", 0.05)]
    video = out / "videos" / "mass_+0.05kg.mp4"
    assert video.is_file() and video.stat().st_size > 1000



def test_cli_bad_policy_is_one_clear_line(capsys, tmp_path):
    from rotation.cli import main

    assert main(["evaluate", "--policy", "x=nowhere", "--out", str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rotate evaluate: error: no bundle directory at 'nowhere'") and "Traceback" not in err


def test_report_json_puts_number_lists_on_one_line_and_leaves_strings_alone():
    from rotation.evaluate.report import json_text

    data = {"ttf": [1.0, 0.25, -3e-05], "note": "keep [  1,  2 ] as written", "names": ["a", "b"], "empty": [],
            "row": {"per_episode": {"ttf": [0.5]}}}
    text = json_text(data)
    assert json.loads(text) == data
    assert '"ttf": [1.0, 0.25, -3e-05]' in text and '"ttf": [0.5]' in text
    assert '"note": "keep [  1,  2 ] as written"' in text


def test_another_contact_model_runs_and_the_report_says_so(setup, tmp_path, monkeypatch):
    """`rotate evaluate --contact-cone elliptic --contact-impratio 10 --contact-noslip-iterations 5`: every env of the
    run compiles those settings, and results.md says they are not the ones the policies were trained with."""
    from envs import core

    seen = []
    task_model = core.task_model

    def spy(cfg, edit=None):
        model, obj, scale = task_model(cfg, edit)
        seen.append((int(model.opt.cone), float(model.opt.impratio), int(model.opt.noslip_iterations)))
        return model, obj, scale

    monkeypatch.setattr(core, "task_model", spy)
    contact = ContactConfig(cone="elliptic", impratio=10.0, noslip_iterations=5)
    rows = job.run(make_cfg(setup, tmp_path / "elliptic", contact=contact))
    assert seen and set(seen) == {(int(mujoco.mjtCone.mjCONE_ELLIPTIC), 10.0, 5)}
    assert all(np.isfinite(r["ttf"]) for r in rows)
    report = (tmp_path / "elliptic" / "results.md").read_text()
    assert "Contact model: elliptic cones, impratio 10, noslip iterations 5" in report
    job.run(make_cfg(setup, tmp_path / "default"))
    assert "Contact model" not in (tmp_path / "default" / "results.md").read_text()
    with pytest.raises(ValueError, match=r"contact.impratio must be in \[1, 100\]"):
        ContactConfig(impratio=0.5)


def test_episode_steps_default_is_the_tasks_own(tmp_path):
    """Unset, --episode-steps is 400 for rotation and the task's own (None) for insertion; given, it is kept."""
    from rotation.cli import build_parser

    def cfg(*extra: str) -> job.Config:
        return job.config_from_args(build_parser().parse_args(["evaluate", "--out", str(tmp_path / "e"), *extra]))

    assert cfg().episode_steps == 400 and cfg("--episode-steps", "40").episode_steps == 40
    assert cfg("--task", "insertion").episode_steps is None
    assert cfg("--task", "insertion", "--episode-steps", "400").episode_steps == 400


def test_contact_options_set_the_whole_model_and_replace_the_hands_contact_randomization(tmp_path):
    """--contact-timeconst / --contact-solimp / --physics-dt reach the env; on a hand whose training randomizes the
    contact (digit360_v4), an explicit contact model is run exactly: none of that randomization is left on."""
    from envs.sim_identity import sim_record
    from rotation.cli import build_parser

    args = build_parser().parse_args(["evaluate", "--contact-timeconst", "0.03", "--contact-solimp", "0.8", "0.9",
                                      "0.002", "--physics-dt", "0.005", "--out", str(tmp_path / "e")])
    cfg = job.config_from_args(args)
    assert cfg.contact == ContactConfig(timeconst=0.03, solimp=(0.8, 0.9, 0.002)) and cfg.physics_dt == 0.005
    assert job.config_from_args(build_parser().parse_args(["evaluate", "--out", str(tmp_path / "f")])).contact is None
    from envs.config import EnvConfig

    v4 = PolicyBundle(BundleConfig(latent_source="privileged", sim=sim_record(EnvConfig(hand="digit360_v4"))))
    env = job.env_config(cfg, v4, Perturbation())
    assert env.hand == "digit360_v4" and env.physics_dt == 0.005 and env.contact == cfg.contact
    rc = env.randomization
    assert rc.impratio is None and rc.contact_timeconst is None and rc.noslip_dropout == 0.0
    assert rc.link_friction is not None  # the rest of the hand's physics stays
    plain = job.env_config(job.Config(out=tmp_path / "g"), v4, Perturbation())
    assert plain.contact.cone == "elliptic" and plain.randomization.impratio == (3.0, 30.0)
    from envs.core import task_model

    model, _, _ = task_model(env)
    assert np.allclose(model.geom_solref[:, 0], 0.03) and np.allclose(model.geom_solimp[:, :3], (0.8, 0.9, 0.002))
    with pytest.raises(ValueError, match="contact.solimp"):
        ContactConfig(solimp=(0.95, 0.9, 0.001))
