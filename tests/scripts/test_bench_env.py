"""scripts/bench_env.py on a tiny budget: every rate is measured and the last line printed is the JSON result."""

from __future__ import annotations

import argparse
import json

from rotation.configs import add_dataclass_arguments, dataclass_from_args


def test_bench_env_tiny(load_script, capsys):
    bench = load_script("bench_env")
    cfg = bench.Config(num_envs=4, nthread=1, subproc_envs=1, seconds=0.05, slice=0.02, rounds=1, action=0.1)
    result = bench.run(cfg)
    out = capsys.readouterr().out.strip().splitlines()
    assert json.loads(out[-1]) == result
    assert {"vec_over_raw", "vec_over_subproc", "raw_steps_per_s", "vec_steps_per_s", "subproc_steps_per_s",
            "num_envs", "nthread", "subproc_envs"} <= set(result)
    assert (result["num_envs"], result["nthread"], result["subproc_envs"], result["substeps"]) == (4, 1, 1, 5)
    for key in ("raw_steps_per_s", "vec_steps_per_s", "sb3_vec_steps_per_s", "subproc_steps_per_s"):
        assert result[key] > 0, key
    assert abs(result["vec_over_raw"] - result["vec_steps_per_s"] / result["raw_steps_per_s"]) < 1e-3
    assert abs(result["vec_over_subproc"] - result["vec_steps_per_s"] / result["subproc_steps_per_s"]) < 1e-3
    assert any(line.startswith("raw mujoco.batch.Batch.step") for line in out)  # the table


def test_bench_env_cli_parses_the_config(load_script):
    bench = load_script("bench_env")
    parser = argparse.ArgumentParser()
    add_dataclass_arguments(parser, bench.Config)
    cfg = dataclass_from_args(bench.Config, parser.parse_args(["--num-envs", "32", "--seconds", "0.5"]))
    assert (cfg.num_envs, cfg.seconds, cfg.nthread, cfg.rounds) == (32, 0.5, 0, 3)
    assert bench.Config().num_envs == 256  # the teacher's num_envs
