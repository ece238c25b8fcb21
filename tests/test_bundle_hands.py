"""A policy acts only on the hand it was trained on (envs.sim_identity, rotation.bundles.check_policy_hand): a bundle
records its hand, the hand's kinematics fingerprint and the contact settings; every job that runs a policy refuses
one trained on another hand, or on a model of its hand that has changed since, in one line with status 1; training
follows the hand of the bundle it starts from."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from envs.config import EnvConfig
from envs.constants import DEFAULT_HAND
from envs.grasp_cache import default_cache_path
from envs.sim_identity import bundle_hand, hand_fingerprint, hand_problem, sim_record
from rotation import cli
from rotation.policy.bundle import PolicyBundle, load_policy_bundle
from rotation.policy.bundle_config import BundleConfig

V4 = "digit360_v4"
OTHER = V4 if DEFAULT_HAND != V4 else "digit360"
"""A hand other than the default one."""


def _bundle(root: Path, name: str, source: str = "privileged", hand: str = V4, sha: str | None = None) -> str:
    sim = sim_record(EnvConfig(hand=hand))
    if sha is not None:
        sim["hand_sha256"] = sha
    return str(PolicyBundle(BundleConfig(latent_source=source, sim=sim)).save(root / name))  # type: ignore[arg-type]


def test_the_fingerprint_names_the_kinematics():
    prints = {hand: hand_fingerprint(hand) for hand in ("digit360", "xela", V4)}
    assert len(set(prints.values())) == 3 and all(len(p) == 64 for p in prints.values())
    assert hand_fingerprint(V4) == prints[V4]  # stable within a process (cached) and across (rounded figures)


def test_hand_problems():
    sim = sim_record(EnvConfig(hand=V4))
    assert sim["hand"] == V4 and sim["contact"]["cone"] == "elliptic" and sim["joint_torque_limits"] == "vendor"
    assert hand_problem(sim, V4) is None
    assert "trained on the digit360_v4 hand, not the digit360 hand" in hand_problem(sim, "digit360")
    assert "model changed" in hand_problem({**sim, "hand_sha256": "0" * 64}, V4)
    # a bundle from before bundles recorded their sim trained on the older model, whose variants share its joints
    assert bundle_hand({}) == "digit360" and hand_problem({}, "digit360") is None and hand_problem({}, "xela") is None
    assert "not the digit360_v4 hand" in hand_problem({}, V4)


def test_a_teacher_records_its_sim_and_a_student_inherits_it(tmp_path):
    teacher = load_policy_bundle(_bundle(tmp_path, "teacher"))
    assert teacher.config.sim["hand"] == V4
    student = teacher.to_student()
    assert student.config.sim == teacher.config.sim
    assert load_policy_bundle(str(student.save(tmp_path / "student"))).config.sim == teacher.config.sim


ROWS = {
    # (argv builder (root -> argv), words of the one-line refusal)
    "evaluate a mix of hands": (lambda r: ["evaluate", "--policy", f"v4={_bundle(r, 't')}", "--policy",
                                           f"old={_bundle(r, 'o', hand='digit360')}", "--episodes", "1", "--out",
                                           str(r / "ev")],
                                "in separate runs"),
    "evaluate a changed model": (lambda r: ["evaluate", "--policy", f"v4={_bundle(r, 't', sha='0' * 64)}",
                                            "--episodes", "1", "--out", str(r / "ev")], "model changed"),
    "view on another hand": (lambda r: ["view", "--policy", _bundle(r, "t", sha="0" * 64), "--out",
                                        str(r / "v.mp4")], "model changed"),
    "collect without touch": (lambda r: ["collect", "--policy", _bundle(r, "t", hand="xela_v4"), "--episodes", "1",
                                         "--out", str(r / "c")], "does not simulate yet"),
    "deploy on a real Allegro": (lambda r: ["deploy", "--hand", "allegro", "--policy",
                                                     _bundle(r, "s", "adaptation", hand="digit360"), "--duration", "1"],
                                 "not the real Allegro's"),
    "deploy on a real LEAP": (lambda r: ["deploy", "--hand", "leap", "--policy", _bundle(r, "s", "adaptation"),
                                         "--duration", "1"], "LEAP model"),
    "deploy a changed model": (lambda r: ["deploy", "--hand", "sim-allegro", "--policy",
                                          _bundle(r, "s", "adaptation", sha="0" * 64), "--duration", "1"],
                               "model changed"),
}


@pytest.mark.parametrize("case", sorted(ROWS))
def test_a_policy_for_another_hand_is_refused_in_one_line(case, tmp_path, monkeypatch, capsys):
    root = tmp_path / "work"
    root.mkdir()
    monkeypatch.chdir(root)
    build, words = ROWS[case]
    argv = build(root)
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    code = cli.main(argv)
    err = capsys.readouterr().err
    lines = [line for line in err.replace("\r", "\n").splitlines() if line.strip()]
    assert code == 1 and "Traceback" not in err, err
    assert lines[-1].startswith(f"rotate {argv[0]}: refused: ") and words in lines[-1], lines[-1]
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before


def test_training_follows_the_hand_of_the_bundle_it_starts_from(tmp_path):
    from rotation.train import student_config, teacher_config

    teacher = _bundle(tmp_path, "teacher")
    cfg = student_config.Config(teacher=teacher, out=tmp_path / "student")
    assert cfg.env.hand == V4 and cfg.env.contact.cone == "elliptic" and cfg.env.randomization.mass[1] == 0.40
    # a teacher run starting from another hand's bundle is refused unless it names that hand
    other = Path(_bundle(tmp_path, "other", hand=OTHER))
    with pytest.raises(ValueError, match=f"init_from: .* trained on the {OTHER} hand, not the {DEFAULT_HAND} hand "
                                         f"\\(pass --hand {OTHER},"):
        teacher_config.Config(init_from=other, out=tmp_path / "t2")
    assert teacher_config.Config(init_from=other, hand=OTHER, out=tmp_path / "t3").env_config().hand == OTHER
    # a student trains on its teacher's hand (the shipped teacher's: the default one), not on another
    with pytest.raises(ValueError, match=f"env.hand: the teacher .* trained on the {DEFAULT_HAND} hand; .* not on "
                                         f"{OTHER}"):
        student_config.Config(teacher="teacher", env=EnvConfig(hand=OTHER), out=tmp_path / "s2")


def test_an_old_hands_grasp_cache_is_refused_in_one_line(tmp_path):
    from envs.grasp_cache import load_default_cache

    with pytest.raises(ValueError, match="generated for the digit360 hand, not for the digit360_v4 hand; generate "
                                         "one with `rotate grasps --hand digit360_v4`"):
        load_default_cache("cup", str(default_cache_path("cup", "digit360")), hand=V4)
    with pytest.raises(ValueError, match="generated for the digit360_v4 hand, not for the digit360 hand"):
        load_default_cache("cup", str(default_cache_path("cup", V4)), hand="digit360")


def test_the_shipped_policies_record_the_default_hand_and_its_contact_model():
    default = EnvConfig(hand=DEFAULT_HAND)
    for name in ("teacher", "student"):
        raw = json.loads((Path(__file__).resolve().parents[1] / "rotation" / "policies" / name / "config.json")
                         .read_text())
        assert raw["sim"] == sim_record(default), name  # the hand, its fingerprint, contact and torque limits
        assert raw["sim"]["contact"] == dataclasses.asdict(default.contact)
        sim = load_policy_bundle(name).config.sim
        assert bundle_hand(sim) == DEFAULT_HAND and hand_problem(sim, DEFAULT_HAND) is None
