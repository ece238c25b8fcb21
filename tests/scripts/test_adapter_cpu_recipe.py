"""scripts/adapter_cpu_recipe.py: the five ablation rows, the oracle, the ensemble, the evaluation, the ablation's
evaluation and the delay sweep chain; every `rotate` command is one its job accepts, a finished row is skipped and a
stopped one resumes."""

from __future__ import annotations

import importlib
import json

import pytest

from rotation import cli
from rotation.configs import dataclass_from_args

JOBS = {"finetune-adapter": "adapters.finetune.job", "ensemble-adapters": "adapters.ensemble_job",
        "evaluate": "rotation.evaluate.job"}


@pytest.fixture(scope="module")
def recipe(load_script):
    return load_script("adapter_cpu_recipe")


def _parsed(args):
    module = importlib.import_module(JOBS[args[0]])
    parsed = cli.build_parser(args[0]).parse_args(args)
    if hasattr(module, "config_from_args"):
        return module.config_from_args(parsed)
    return dataclass_from_args(module.Config, parsed)


def _config(recipe, out):
    return recipe.Config(student="student", teacher="teacher", encoder="sparshx-tinier-sim", out=out, progress=False)


def test_every_step_is_listed_and_the_training_and_evaluation_commands_parse(recipe, tmp_path):
    out = tmp_path / "r"
    steps = recipe.commands(_config(recipe, out))
    rows = [row for row, _ in recipe.ROWS]
    assert [w.split(":")[0] for w, _ in steps] == [*rows, "the oracle-latent student", "the ensemble",
                                                    "the evaluation", "the ablation", "ttf against the delay"]
    trained = [_parsed(args) for _, args in steps[:5]]
    assert {c.touch_delay for c in trained} == {"measured"} and {c.seed for c in trained} == {31}
    assert [c.modalities for c in trained] == ["img,mic,imu,pressure", "img", "mic,imu,pressure", "imu,pressure",
                                               "pressure"]
    assert [c.tracking for c in trained] == [False, False, False, True, True]
    assert [getattr(c, "blind_touch", False) for c in trained] == [False] * 4 + [True]
    evaluation, ablation = _parsed(steps[-3][1]), _parsed(steps[-2][1])
    assert list(evaluation.policies) == ["teacher", "student", "oracle", "ensemble"]
    assert evaluation.conditions == recipe.CONDITIONS and evaluation.touch_delay == "measured"
    assert list(ablation.policies) == rows and ablation.conditions == recipe.ABLATION_CONDITIONS
    assert (ablation.seed, ablation.touch_delay) == (evaluation.seed, "measured")  # the rows pair with step 4
    assert ablation.episodes == 64 < evaluation.episodes == 128
    sweep = steps[-1][1]
    assert sweep[sweep.index("--conditions") + 1:sweep.index("--episodes")] == list(recipe.SWEEP_CONDITIONS)
    assert steps[5][1][1].endswith("oracle_latent.py") and steps[-1][1][1].endswith("delay_sweep.py")
    ensemble = steps[6][1]
    assert ensemble[ensemble.index("--members") + 1:ensemble.index("--out")] == [
        str(out / "members" / row / "bundle") for row in recipe.ENSEMBLE]


def test_a_finished_row_is_skipped_and_a_stopped_one_resumes(recipe, tmp_path):
    out = tmp_path / "r"
    done = out / "members" / "all_modalities" / "bundle"
    done.mkdir(parents=True)
    (done / "config.json").write_text(json.dumps({"card": {"env_steps": 24_000}}))
    stopped = out / "members" / "image_only"
    (stopped / "bundle").mkdir(parents=True)
    (stopped / "bundle" / "config.json").write_text(json.dumps({"card": {"env_steps": 8000,
                                                                         "interrupted": "stopped by SIGINT"}}))
    (stopped / "ckpt_000000008000.pt").write_bytes(b"")
    steps = dict(recipe.commands(_config(recipe, out)))
    assert not any(w.startswith("all_modalities") for w in steps)
    assert steps["image_only: resume"] == ["finetune-adapter", "--out", str(stopped), "--resume", "--no-progress"]
    with pytest.raises(ValueError, match="--student, --teacher, --encoder"):
        recipe.Config()
