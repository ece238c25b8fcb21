"""scripts/teacher_cpu_recipe.py: the five teacher stages and the two student stages chain, skip what is finished
and resume what was stopped (on the first hand; another hand's recipe adds two stages)."""

from __future__ import annotations

import json
import shutil

import pytest

from envs.config import EnvConfig
from envs.constants import DEFAULT_HAND
from envs.grasp_cache import default_cache_path
from envs.sim_identity import sim_record
from rotation import cli
from rotation.configs import save_config
from rotation.evaluate import job as evaluate_job
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig
from rotation.train import finetune_student, student, teacher

FIRST = "digit360"
"""The first hand, whose recipe (stages 1-5, its shipped hold-checked grasps) most tests here run; the recipe's
default is DEFAULT_HAND."""


@pytest.fixture(scope="module")
def recipe(load_script):
    return load_script("teacher_cpu_recipe")


def _fake_bundle(path, card, sim=None):
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps({"card": card} | ({"sim": sim} if sim else {})))


def _parsed(args):
    """The config a `rotate` command line makes, parsed and validated by its job's own config_from_args."""
    module = {"train-teacher": teacher, "train-student": student, "finetune-student": finetune_student,
              "evaluate": evaluate_job}[args[0]]
    return module.config_from_args(cli.build_parser(args[0]).parse_args(args))


def _finished_teacher(recipe, out):
    """Stage 0 and the five teacher stages, finished."""
    (out / "grasps_unchecked").mkdir(parents=True)
    (out / "grasps_unchecked" / "grasps_cup.npz").write_bytes(b"")
    for name, steps, _ in recipe.STAGES:
        _fake_bundle(out / name / "bundle", {"steps": steps})


def test_the_recipe_trains_the_default_hand_unless_told(recipe, tmp_path):
    assert recipe.Config(out=tmp_path).hand == DEFAULT_HAND
    stage1 = dict((w.split(":")[0], a) for w, a in recipe.commands(recipe.Config(out=tmp_path)))["stage1"]
    assert stage1[stage1.index("--hand") + 1] == DEFAULT_HAND


def test_every_stage_is_a_valid_command_of_its_job(recipe, tmp_path):
    out = tmp_path / "recipe"
    todo = recipe.commands(recipe.Config(out=out, progress=False, hand=FIRST))
    assert [what.split(":")[0] for what, _ in todo] == ["stage 0", "stage1", "stage2", "stage3", "stage4",
                                                        "stage5", "student", "student_rl", "evaluation",
                                                        "evaluation"]
    assert todo[0][1][-2:] == ["--hand", FIRST]  # its grasps, whatever the jobs' default hand
    # with the files each stage reads in place, the options parse and validate as the job's own Config
    (out / "grasps_unchecked").mkdir(parents=True)
    shutil.copy(default_cache_path("cup", FIRST), out / "grasps_unchecked" / "grasps_cup.npz")
    for name, _, _ in recipe.STAGES[:-1]:
        _fake_bundle(out / name / "bundle", {"steps": 1, "interrupted": "stopped"})  # not finished: still to run
    # the fine-tune loads the distilled student: a bundle recording no sim, of the first hand like the stages'
    distilled = PolicyBundle(BundleConfig()).to_student().save(out / "student" / "bundle")
    config = json.loads((distilled / "config.json").read_text())
    config["card"] = {"env_steps": 1, "interrupted": "stopped"}
    (distilled / "config.json").write_text(json.dumps(config))
    configs = {}
    for _, args in recipe.commands(recipe.Config(out=out, progress=False, hand=FIRST)):
        configs.setdefault(args[0], []).append(_parsed(args))
    assert list(configs) == ["train-teacher", "train-student", "finetune-student", "evaluate"]
    stages = configs["train-teacher"]
    assert {c.hand for c in stages} == {FIRST}
    assert [c.seed for c in stages] == [0, 3, 7, 11, 13]
    assert [c.fall_reward for c in stages] == [-20.0, -20.0, -60.0, -35.0, -60.0]
    assert [c.rotate_back_clip for c in stages] == [0.5, 5.0, 5.0, 5.0, 5.0]
    # stages 1-2 start from the grasps without the hold check, 3-5 from the shipped ones (which evaluation uses)
    assert [bool(c.grasp_cache) for c in stages] == [True, True, False, False, False]
    assert stages[0].init_from is None and [c.init_from for c in stages[1:]] == [
        out / name / "bundle" for name, _, _ in recipe.STAGES[:-1]]
    assert sum(c.total_steps for c in stages) == 37_060_608
    # the student: the report's two commands, each from the bundle of the stage before it
    [distill] = configs["train-student"]
    assert (distill.teacher, distill.out) == (str(out / "stage5" / "bundle"), out / "student")
    assert (distill.total_steps, distill.num_envs, distill.seed, distill.resume) == (6_000_000, 64, 0, False)
    assert not distill.progress and not distill.env.grasp_cache  # the shipped grasps, as stage 5's
    [rl] = configs["finetune-student"]
    assert (rl.student, rl.out, rl.init_from) == (str(out / "student" / "bundle"), out / "student_rl", None)
    assert (rl.total_steps, rl.checkpoint_every, rl.seed, rl.fall_reward) == (4_000_000, 500_000, 12, -60.0)
    assert not rl.overlap and not rl.progress and not rl.grasp_cache and rl.hand == FIRST
    # teacher and final student on the same fresh seeds
    evaluation, contact = configs["evaluate"]
    assert evaluation.policies == {"teacher_cpu": str(out / "stage5" / "bundle"),
                                   "student_cpu": str(out / "student_rl" / "bundle")}
    assert (evaluation.conditions, evaluation.episodes, evaluation.seed) == (("nominal",), 128, 3_300_000)
    assert evaluation.out == out / "evaluation_student" and evaluation.contact is None
    # and again under a contact model the hand never trains on (the shipped hand's is pyramidal: elliptic here)
    assert contact.policies == evaluation.policies and contact.seed == evaluation.seed
    assert contact.out == out / "evaluation_contact"
    assert (contact.contact.cone, contact.contact.impratio, contact.contact.noslip_iterations) == ("elliptic", 10, 10)
    v4 = recipe.commands(recipe.Config(out=tmp_path / "v4", hand="digit360_v4"))[-1][1]
    assert v4[v4.index("--contact-cone") + 1:v4.index("--contact-noslip-iterations") + 2] == [
        "pyramidal", "--contact-impratio", "3", "--contact-noslip-iterations", "0"]


def test_another_hand_gets_the_speed_stage_between_stages_4_and_5_and_the_hold_stage_after(recipe, tmp_path):
    """On the vendor-kinematics hand the teacher trains a stage 4b (rotate cap 1.0 rad/s, half the pose penalty,
    fall cost 35) from stage 4's bundle, stage 5 continues from it, and stage 6 (fall cost 60 with 4b's reward)
    from stage 5; the student distills stage 6 and the evaluation takes it as the teacher."""
    out = tmp_path / "v4"
    todo = recipe.commands(recipe.Config(out=out, hand="digit360_v4"))
    names = [what.split(":")[0] for what, _ in todo]
    assert names[names.index("stage4"):names.index("student")] == ["stage4", "stage4b", "stage5", "stage6"]
    hold, distill, evaluation = (dict((w.split(":")[0], a) for w, a in todo)[n] for n in ("stage6", "student",
                                                                                          "evaluation"))
    assert hold[hold.index("--init-from") + 1] == str(out / "stage5" / "bundle")
    assert [hold[hold.index(o) + 1] for o in ("--fall-reward", "--rotate-clip", "--pose-diff-reward")] == [
        "-60", "1.0", "-0.05"]
    assert distill[distill.index("--teacher") + 1] == str(out / "stage6" / "bundle")
    assert f"teacher_cpu={out / 'stage6' / 'bundle'}" in evaluation
    sim = sim_record(EnvConfig(hand="digit360_v4"))
    (out / "grasps_checked").mkdir(parents=True)  # the recipe's own hold-checked grasps, which stages 3 on read
    shutil.copy(default_cache_path("cup", "digit360_v4"), out / "grasps_checked")
    for name in ("stage1", "stage2", "stage3", "stage4"):
        _fake_bundle(out / name / "bundle", {"steps": 1, "interrupted": "stopped"}, sim)
    args = {what.split(":")[0]: a for what, a in recipe.commands(recipe.Config(out=out, hand="digit360_v4"))}
    speed = _parsed(args["stage4b"])
    assert (speed.rotate_clip, speed.pose_diff_reward, speed.fall_reward, speed.seed) == (1.0, -0.05, -35.0, 17)
    assert speed.init_from == out / "stage4" / "bundle" and speed.hand == "digit360_v4"
    assert speed.total_steps == 5_996_544
    last = args["stage5"]  # from stage 4b's bundle, with the usual reward (its bundle is not there to parse)
    assert last[last.index("--init-from") + 1] == str(out / "stage4b" / "bundle")
    assert "--rotate-clip" not in last and "--pose-diff-reward" not in last


def test_teacher_only_leaves_the_student_out_and_evaluates_the_teacher_alone(recipe, tmp_path, capsys):
    out = tmp_path / "recipe"
    assert recipe.main(["--out", str(out), "--teacher-only", "--dry-run", "--hand", FIRST]) == 0
    printed = capsys.readouterr().out
    assert "rotate train-teacher" in printed and "student" not in printed and not out.exists()
    todo = recipe.commands(recipe.Config(out=out, teacher_only=True, hand=FIRST))
    assert [what.split(":")[0] for what, _ in todo] == ["stage 0", "stage1", "stage2", "stage3", "stage4",
                                                        "stage5", "evaluation", "evaluation"]
    evaluation = _parsed(todo[-2][1])
    assert evaluation.policies == {"teacher_cpu": str(out / "stage5" / "bundle")}
    assert evaluation.out == out / "evaluation"
    # its evaluation is not the full recipe's: a later run without --teacher-only still evaluates the student
    (out / "evaluation").mkdir(parents=True)
    (out / "evaluation" / "results.md").write_text("# Evaluation\n")
    assert recipe.commands(recipe.Config(out=out, teacher_only=True, contact_check=False, hand=FIRST))[-1][0] \
        .startswith("stage5")
    assert recipe.commands(recipe.Config(out=out, contact_check=False, hand=FIRST))[-1][1][-1] == str(
        out / "evaluation_student")


def test_student_from_picks_the_teacher_stage_and_refuses_a_student_of_another(recipe, tmp_path, capsys):
    """--student-from names the stage the student distills and the evaluation takes as the teacher; a student folder
    started from another teacher is refused in one line, not resumed; an unknown stage is refused too."""
    out = tmp_path / "recipe"
    _finished_teacher(recipe, out)
    todo = dict((w.split(":")[0], a) for w, a in recipe.commands(recipe.Config(out=out, student_from="stage3",
                                                                               hand=FIRST)))
    assert _parsed(todo["student"]).teacher == str(out / "stage3" / "bundle")
    assert f"teacher_cpu={out / 'stage3' / 'bundle'}" in todo["evaluation"]
    distill = out / "student"
    save_config(student.Config(teacher=str(out / "stage5" / "bundle"), out=distill, total_steps=6_000_000),
                distill / "config.json")
    (distill / "ckpt_000003125.pt").write_bytes(b"")
    with pytest.raises(ValueError, match="move that folder aside"):
        recipe.commands(recipe.Config(out=out, student_from="stage3", hand=FIRST))
    assert recipe.main(["--out", str(out), "--student-from", "stage3", "--dry-run", "--hand", FIRST]) != 0
    assert "move that folder aside" in capsys.readouterr().err
    assert [w.split(":")[0] for w, _ in recipe.commands(recipe.Config(out=out, eval_episodes=0, hand=FIRST))][0] \
        == "student"
    with pytest.raises(ValueError, match="student_from: one of"):
        recipe.Config(out=out, student_from="stage4b", hand=FIRST)  # the first hand's recipe has no speed stage


def test_finished_stages_are_skipped_and_a_stopped_one_resumes(recipe, tmp_path):
    out = tmp_path / "recipe"
    (out / "grasps_unchecked").mkdir(parents=True)
    (out / "grasps_unchecked" / "grasps_cup.npz").write_bytes(b"")
    steps1, steps2 = recipe.STAGES[0][1], recipe.STAGES[1][1]
    _fake_bundle(out / "stage1" / "bundle", {"steps": steps1})
    _fake_bundle(out / "stage2" / "bundle", {"steps": 123, "interrupted": "stopped by SIGTERM"})
    (out / "stage2" / "checkpoints").mkdir()
    (out / "stage2" / "checkpoints" / "last.zip").write_bytes(b"")
    todo = recipe.commands(recipe.Config(out=out, eval_episodes=0, teacher_only=True, hand=FIRST))
    assert [what.split(":")[0] for what, _ in todo] == ["stage2", "stage3", "stage4", "stage5"]
    assert todo[0][1] == ["train-teacher", "--resume", str(out / "stage2" / "checkpoints" / "last.zip"),
                          "--total-steps", str(steps2)]
    assert "--init-from" in todo[1][1] and str(out / "stage2" / "bundle") in todo[1][1]


def test_finished_student_stages_are_skipped_and_a_stopped_one_resumes(recipe, tmp_path):
    out = tmp_path / "recipe"
    _finished_teacher(recipe, out)
    distill_steps, rl_steps = (steps for _, _, steps, _ in recipe.STUDENT_STAGES)
    assert recipe.DISTILL_CHECKPOINTS == student.CHECKPOINT_GLOB

    def todo():
        cfg = recipe.Config(out=out, eval_episodes=0, progress=False, hand=FIRST)
        return [(what.split(":")[0], args) for what, args in recipe.commands(cfg)]

    # the distillation stopped (its bundle says so, beside its checkpoints): it resumes with the run's own options
    distill = out / "student"
    save_config(student.Config(teacher=str(out / "stage5" / "bundle"), out=distill, total_steps=distill_steps),
                distill / "config.json")
    (distill / "ckpt_000003125.pt").write_bytes(b"")
    _fake_bundle(distill / "bundle", {"env_steps": 200_000, "interrupted": "stopped by SIGINT at 200000 of 6000000",
                                      "config": {"total_steps": distill_steps}})
    [(what, args), (what_rl, args_rl)] = todo()
    assert (what, what_rl) == ("student", "student_rl")
    assert args == ["train-student", "--out", str(distill), "--resume", "--total-steps", str(distill_steps),
                    "--no-progress"]
    resumed = _parsed(args)
    assert resumed.resume and resumed.teacher == str(out / "stage5" / "bundle") and resumed.out == distill
    assert args_rl[:3] == ["finetune-student", "--student", str(distill / "bundle")]
    # finished: at the full length; also when a resume found nothing left to train (it logs no point)
    for card in ({"env_steps": distill_steps, "config": {"total_steps": distill_steps}},
                 {"env_steps": 0, "config": {"total_steps": distill_steps}}):
        (distill / "bundle" / "config.json").write_text(json.dumps({"card": card}))
        assert [what for what, _ in todo()] == ["student_rl"]
    # the fine-tune stopped: it resumes from its last checkpoint; finished, nothing is left
    rl = out / "student_rl"
    _fake_bundle(rl / "bundle", {"steps": 1_015_808, "interrupted": "stopped by SIGTERM at 1015808 of 4000000"})
    (rl / "checkpoints").mkdir()
    (rl / "checkpoints" / "last.zip").write_bytes(b"")
    assert todo() == [("student_rl", ["finetune-student", "--resume", str(rl / "checkpoints" / "last.zip"),
                                      "--total-steps", str(rl_steps), "--no-progress"])]
    (rl / "bundle" / "config.json").write_text(json.dumps({"card": {"steps": rl_steps + 14_080}}))
    assert todo() == []
    # a shorter stage is not the recipe's: it is not finished
    (rl / "bundle" / "config.json").write_text(json.dumps({"card": {"steps": rl_steps // 2}}))
    assert [what for what, _ in todo()] == ["student_rl"]


def test_a_tiny_recipe_runs_end_to_end_and_a_second_call_has_nothing_left(recipe, tmp_path, monkeypatch, capsys):
    """The real jobs, with the stages shrunk to a few updates: each stage starts from the previous one's bundle, and
    stopped student stages resume from their checkpoints."""
    tiny = ["--num-envs", "8", "--n-steps", "16", "--batch-size", "64", "--n-epochs", "1", "--episode-steps", "30",
            "--no-overlap"]
    stages = tuple((name, 256, [*(o for o in options if o.startswith("--init-from") or o == "{prev}"), *tiny,
                                "--seed", str(i)]) for i, (name, _, options) in enumerate(recipe.STAGES))
    student_stages = (
        ("student", "train-student", 64,
         ["--teacher", "{prev}", "--out", "{run}", "--total-steps", "{steps}", "--num-envs", "4", "--checkpoint-every",
          "32", "--log-every", "4", "--env.episode-steps", "30", "--seed", "0"]),
        ("student_rl", "finetune-student", 256,
         ["--student", "{prev}", "--out", "{run}", "--total-steps", "{steps}", *tiny, "--checkpoint-every", "128",
          "--seed", "12", "--fall-reward", "-60"]),
    )
    monkeypatch.setattr(recipe, "STAGES", stages)
    monkeypatch.setattr(recipe, "STUDENT_STAGES", student_stages)
    out = tmp_path / "recipe"
    (out / "grasps_unchecked").mkdir(parents=True)
    shutil.copy(default_cache_path("cup", FIRST), out / "grasps_unchecked" / "grasps_cup.npz")
    assert recipe.main(["--out", str(out), "--eval-episodes", "8", "--no-progress", "--hand", FIRST]) == 0
    cards = [json.loads((out / name / "bundle" / "config.json").read_text())["card"] for name, _, _ in stages]
    assert [c["steps"] for c in cards] == [256] * 5 and {c["train_config"]["hand"] for c in cards} == {FIRST}
    assert [c["train_config"]["init_from"] for c in cards] == [None, *(str(out / n / "bundle") for n, _, _ in
                                                                     stages[:-1])]
    distilled = json.loads((out / "student" / "bundle" / "config.json").read_text())["card"]
    assert (distilled["trained_by"], distilled["teacher"], distilled["env_steps"]) == (
        "rotate train-student", str(out / "stage5" / "bundle"), 64)
    finetuned = json.loads((out / "student_rl" / "bundle" / "config.json").read_text())["card"]
    assert (finetuned["role"], finetuned["steps"]) == ("student", 256)
    assert finetuned["finetuned_from"]["bundle"] == str(out / "student" / "bundle")
    results = (out / "evaluation_student" / "results.md").read_text()
    assert "| nominal" in results and "teacher_cpu" in results and "student_cpu" in results
    contact = (out / "evaluation_contact" / "results.md").read_text()
    assert "teacher_cpu" in contact and "Contact model: elliptic" in contact, contact
    capsys.readouterr()
    assert recipe.main(["--out", str(out), "--no-progress", "--hand", FIRST]) == 0
    assert "every stage is done" in capsys.readouterr().out

    # both student stages stopped halfway (their bundles say so; the checkpoints after it are lost): they resume
    ckpts = sorted((out / "student").glob("ckpt_*.pt"))
    assert [p.name for p in ckpts] == ["ckpt_000000008.pt", "ckpt_000000016.pt"]
    ckpts[-1].unlink()
    rl_ckpts = out / "student_rl" / "checkpoints"
    shutil.copy(rl_ckpts / "step_0000000128.zip", rl_ckpts / "last.zip")  # with the record that its run wrote it
    shutil.copy(rl_ckpts / "step_0000000128.zip.owner.json", rl_ckpts / "last.zip.owner.json")
    (rl_ckpts / "step_0000000256.zip").unlink()
    for name, card in (("student", distilled), ("student_rl", finetuned)):
        (out / name / "bundle" / "config.json").write_text(
            json.dumps({"card": card | {"interrupted": "stopped by SIGTERM"}}))
    assert recipe.main(["--out", str(out), "--no-progress", "--hand", FIRST]) == 0
    said = [line for line in capsys.readouterr().out.splitlines() if line.startswith("teacher_cpu_recipe: ")]
    assert said == [f"teacher_cpu_recipe: student: resume at {out / 'student' / 'ckpt_000000008.pt'}",
                    f"teacher_cpu_recipe: student_rl: resume at {rl_ckpts / 'last.zip'}",
                    f"teacher_cpu_recipe: done; the teacher is {out / 'stage5' / 'bundle'}; the student is "
                    f"{out / 'student_rl' / 'bundle'}; evaluated in {out / 'evaluation_student' / 'results.md'} and "
                    f"{out / 'evaluation_contact' / 'results.md'}"]
    distilled = json.loads((out / "student" / "bundle" / "config.json").read_text())["card"]
    finetuned = json.loads((out / "student_rl" / "bundle" / "config.json").read_text())["card"]
    assert "interrupted" not in distilled and distilled["env_steps"] == 64
    assert "interrupted" not in finetuned and finetuned["steps"] == 256
    assert finetuned["resumed_from"] == str(rl_ckpts / "last.zip")
    assert recipe.main(["--out", str(out), "--no-progress", "--hand", FIRST]) == 0
    assert "every stage is done" in capsys.readouterr().out
