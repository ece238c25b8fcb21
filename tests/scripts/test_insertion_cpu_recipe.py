"""scripts/insertion_cpu_recipe.py: demonstrations, one imitation training per row and the closed-loop evaluation;
every command is one its job accepts, a trained row is skipped and a stopped training resumes."""

from __future__ import annotations

import pytest

from rotation import cli
from rotation.configs import dataclass_from_args
from rotation.evaluate import options as evaluate_options
from rotation.il import job as train_il
from rotation.jobs import demos


@pytest.fixture(scope="module")
def recipe(load_script):
    return load_script("insertion_cpu_recipe")


def _parsed(args):
    parsed = cli.build_parser(args[0]).parse_args(args)
    if args[0] == "evaluate":
        return evaluate_options.config_from_args(parsed)
    return dataclass_from_args({"demos": demos, "train-il": train_il}[args[0]].Config, parsed)


def test_every_step_is_listed_and_parses(recipe, tmp_path):
    out = tmp_path / "r"
    cfg = recipe.Config(out=out, rows=("camera", "touch_all", "touch_e2e", "skin"), skin_encoder="skin_run",
                        progress=False)
    steps = recipe.commands(cfg)
    assert [w for w, _ in steps] == ["demonstrations (Digit 360 hand)", "demonstrations (Xela hand)", "train camera",
                                     "train touch_all", "train touch_e2e", "train skin",
                                     "evaluate 4 policies over 100 trials"]
    parsed = [_parsed(args) for _what, args in steps]
    assert [p.hand for p in parsed[:2]] == ["digit360_v4", "xela_v4"] and parsed[0].episodes == 100
    camera, touch_all, e2e, skin = parsed[2:6]
    assert (camera.touch, touch_all.touch, e2e.touch, skin.touch) == ("none", "all", "e2e", "skin")
    assert touch_all.encoder == "sparshx-tinier-sim" and skin.encoder == "skin_run"
    assert skin.demos == (out / "demos_xela",) and camera.demos == (out / "demos",)
    assert (e2e.steps, e2e.batch_size, touch_all.steps) == (1500, 8, 3000)
    evaluate = parsed[6]
    assert evaluate.task == "insertion" and evaluate.episodes == 100 and evaluate.seed == 500_000
    assert dict(evaluate.policies)["touch_all"] == str(out / "il_touch_all" / "bundle")
    # a row with its bundle is done; one with a checkpoint resumes; the evaluation is skipped once it wrote results
    (out / "il_camera" / "bundle").mkdir(parents=True)
    (out / "il_touch_all").mkdir()
    (out / "il_touch_all" / "checkpoint.pt").write_bytes(b"")
    steps = dict(recipe.commands(cfg))
    assert "train camera" not in steps and "--resume" in steps["train touch_all"]
    (out / "eval").mkdir()
    (out / "eval" / "results.json").write_text("[]")
    assert not any(w.startswith("evaluate") for w, _ in recipe.commands(cfg))
    assert (parsed[0].noise_m, parsed[0].noise_rad, parsed[0].expert_align) == (0.0, 0.0, "feel")
    noisy = [_parsed(args) for _w, args in recipe.commands(recipe.Config(
        out=out, rows=("camera", "skin"), skin_encoder="s", noise_m=0.0005, noise_rad=0.01, expert_align="state",
        progress=False))[:2]]
    assert {(d.noise_m, d.noise_rad, d.expert_align) for d in noisy} == {(0.0005, 0.01, "state")}


def test_dagger_rounds_drive_each_row_with_its_latest_policy_and_train_on_every_round(recipe, tmp_path):
    out = tmp_path / "r"
    cfg = recipe.Config(out=out, rows=("camera", "skin"), skin_encoder="s", dagger_rounds=2, dagger_episodes=40,
                        progress=False)
    steps = recipe.commands(cfg)
    assert [w for w, _ in steps][3:9] == ["DAgger round 1 of camera", "train camera after round 1",
                                          "DAgger round 2 of camera", "train camera after round 2", "train skin",
                                          "DAgger round 1 of skin"]
    parsed = dict((w, _parsed(args)) for w, args in steps)
    round2 = parsed["DAgger round 2 of camera"]
    assert round2.policy == str(out / "il_camera_r1" / "bundle") and round2.seed == 2 and round2.episodes == 40
    assert round2.out == out / "dagger_camera_2" and round2.noise_m == 0.0 and round2.hand == "digit360_v4"
    assert parsed["DAgger round 1 of skin"].hand == "xela_v4"
    assert parsed["train camera after round 2"].demos == (out / "demos", out / "dagger_camera_1",
                                                         out / "dagger_camera_2")
    assert parsed["train camera after round 2"].out == out / "il_camera_r2"
    evaluate = parsed["evaluate 4 policies over 100 trials"]
    assert dict(evaluate.policies) == {"camera": str(out / "il_camera_r2" / "bundle"),
                                       "skin": str(out / "il_skin_r2" / "bundle"),
                                       "camera_bc": str(out / "il_camera" / "bundle"),
                                       "skin_bc": str(out / "il_skin" / "bundle")}
    (out / "il_camera_r1" / "bundle").mkdir(parents=True)  # a round trained is skipped, its demos still listed
    names = [w for w, _ in recipe.commands(cfg)]
    assert "train camera after round 1" not in names and "DAgger round 1 of camera" in names


@pytest.mark.parametrize("options, message", [
    ({"dagger_rounds": -1}, "dagger_rounds must be in"),
    ({"dagger_episodes": 0}, "dagger_episodes must be >= 1"),
    ({"rows": ("camera", "lidar")}, "rows: give distinct rows"),
    ({"rows": ("camera", "camera")}, "rows: give distinct rows"),
    ({"rows": ("skin",)}, "the skin row needs --skin-encoder"),
    ({"eval_seed": 10}, "eval_seed must be >= episodes"),
    ({"trials": 0}, "trials must be >= 1"),
])
def test_bad_settings_are_refused_in_one_line(recipe, tmp_path, options, message):
    with pytest.raises(ValueError, match=message):
        recipe.Config(out=tmp_path / "r", **options)


def test_dry_run_runs_nothing(recipe, tmp_path, capsys):
    assert recipe.main(["--out", str(tmp_path / "r"), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "rotate demos --task insertion" in printed and "rotate evaluate --task insertion" in printed
    assert not (tmp_path / "r").exists()
