"""scripts/bench_skin.py on a tiny budget: the env measurement runs and the last line printed is the JSON result."""

from __future__ import annotations

import json

import pytest


def test_bench_skin_tiny(load_script, capsys):
    bench = load_script("bench_skin")
    assert bench.main(["--num-envs", "2", "--steps", "8", "--rounds", "1", "--nthread", "1", "--only", "env"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {"skin_over_plain", "skin_over_xela_off", "plain_steps_per_s", "skin_steps_per_s"} <= set(result)
    assert result["skin_over_plain"] > 0
    with pytest.raises(ValueError, match="unknown measurement"):
        bench.run(bench.Config(only=("nope",)))


def test_bench_skin_encoder_latency(load_script, capsys):
    bench = load_script("bench_skin")
    result = bench.run(bench.Config(only=("encoder",), encoder_size="tinier", iters=1, threads=1))
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == result
    assert result["skin_tinier_ms"] > 0 and result["skin_tinier_params"] == 938_112 and result["encoder_threads"] == 1
    with pytest.raises(ValueError, match="encoder_size"):
        bench.run(bench.Config(only=("encoder",), encoder_size="huge"))
