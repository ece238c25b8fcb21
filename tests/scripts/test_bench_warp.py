"""scripts/bench_warp.py on a tiny budget (Warp's CPU device, a few worlds): every rate is measured and the last
line printed is the JSON result."""

from __future__ import annotations

import argparse
import json

import pytest

from rotation.configs import add_dataclass_arguments, dataclass_from_args


def test_bench_warp_tiny(load_script, capsys):
    pytest.importorskip("mujoco_warp", reason="the warp backend needs the [warp] extra: pip install -e '.[warp]'")
    bench = load_script("bench_warp")
    cfg = bench.Config(worlds=(2, 3), device="cpu", steps=2, warmup=1, train_worlds=2, train_iterations=1,
                       n_steps=2, n_epochs=1, cpu_envs=4, cpu_steps=2, nthread=1,
                       hand="digit360")  # the warp backend does not simulate the digit360_v4 hand's physics yet
    result = bench.run(cfg)
    out = capsys.readouterr().out.strip().splitlines()
    assert json.loads(out[-1]) == result
    for key in ("warp_env_steps_per_s", "warp_train_steps_per_s", "cpu_env_steps_per_s"):
        assert result[key] > 0, key
    assert set(result["warp_env_steps_per_s_by_worlds"]) == {"2", "3"}
    assert result["warp_env_steps_per_s"] == max(result["warp_env_steps_per_s_by_worlds"].values())


def test_bench_warp_cli_parses_the_config(load_script):
    bench = load_script("bench_warp")
    parser = argparse.ArgumentParser()
    add_dataclass_arguments(parser, bench.Config)
    cfg = dataclass_from_args(bench.Config, parser.parse_args(["--worlds", "1024", "4096", "--device", "cpu"]))
    assert cfg.worlds == (1024, 4096) and cfg.device == "cpu" and cfg.train_worlds == 8192
    with pytest.raises(ValueError, match="worlds"):
        bench.Config(worlds=())
    with pytest.raises(ValueError, match="hand: the warp backend simulates the digit360 and xela hands, not "
                                         "'digit360_v4'"):
        bench.Config(hand="digit360_v4")
