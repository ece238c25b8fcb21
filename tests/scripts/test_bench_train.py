"""scripts/bench_train.py on a tiny budget: both rates measured, the last line is the JSON result."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bench_train.py"


def load_script():
    spec = importlib.util.spec_from_file_location("bench_train", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is created
    spec.loader.exec_module(module)
    return module


def test_bench_train_tiny(tmp_path, capsys):
    bench = load_script()
    argv = ["--num-envs", "4", "--env-steps", "64", "--train-steps", "64", "--n-steps", "16", "--batch-size", "32",
            "--n-epochs", "1", "--nthread", "1", "--torch-threads", "1"]
    assert bench.main(argv) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    result = json.loads(last)
    assert result["train_steps_timed"] == 64 and result["num_envs"] == 4
    assert result["env_steps_per_s"] > 0 and result["train_steps_per_s"] > 0
    assert abs(result["train_over_env"] - result["train_steps_per_s"] / result["env_steps_per_s"]) < 1e-3
