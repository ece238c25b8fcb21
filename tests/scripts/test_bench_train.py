"""scripts/bench_train.py on a tiny budget: both rates and the costs measured, the last line is the JSON result;
the ceiling's arithmetic."""

from __future__ import annotations

import json


def test_bench_train_tiny(load_script, tmp_path, capsys):
    bench = load_script("bench_train")
    argv = ["--num-envs", "4", "--env-steps", "64", "--train-steps", "64", "--n-steps", "16", "--batch-size", "32",
            "--n-epochs", "1", "--nthread", "1", "--torch-threads", "1"]
    assert bench.main(argv) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    result = json.loads(last)
    assert result["train_steps_timed"] == 64 and result["num_envs"] == 4
    assert result["env_steps_per_s"] > 0 and result["train_steps_per_s"] > 0
    assert abs(result["train_over_env"] - result["train_steps_per_s"] / result["env_steps_per_s"]) < 1e-3
    assert 0.0 < result["train_over_env_ceiling"] <= 1.0
    assert result["update_s"] > 0 and result["inference_s"] > 0 and result["physics_core_s"] > 0


def test_ceiling_is_the_cpu_time_bound(load_script):
    bench = load_script("bench_train")
    # the physics alone fills 2 cores for 1 s of wall (2 core-s); an update of 1 s and inference of 0.2 s leave
    # (2 + 1 + 0.2) / 2 = 1.6 s of wall per rollout at best: 1 / 1.6 of the env's speed
    assert abs(bench.ceiling(1.0, 2.0, 2, 1.0, 0.2) - 1.0 / 1.6) < 1e-9
    # physics that does not scale over cores (1 core-s on 1 s of wall): the rest fits on the idle core
    assert bench.ceiling(1.0, 1.0, 2, 0.5, 0.0) == 1.0
