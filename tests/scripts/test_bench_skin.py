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
    assert result["skin_tinier_p95_ms"] >= result["skin_tinier_ms"]
    assert result["skin_tinier_hz"] == pytest.approx(1e3 / result["skin_tinier_ms"], rel=0.01)
    with pytest.raises(ValueError, match="encoder_size"):
        bench.run(bench.Config(only=("encoder",), encoder_size="huge"))


def test_bench_skin_times_a_given_encoder(load_script, capsys):
    """--checkpoint times that encoder (here the shipped one, by name); a Sparsh-X file is refused."""
    bench = load_script("bench_skin")
    result = bench.run(bench.Config(only=("encoder",), checkpoint="sparshskin-tiny-sim", iters=1, threads=1))
    assert result["skin_tinier_params"] == 938_112 and "sparshskin-tiny-sim" in capsys.readouterr().out
    with pytest.raises(ValueError, match="not a Sparsh-skin encoder"):
        bench.run(bench.Config(only=("encoder",), checkpoint="sparshx-tinier-sim", iters=1))
