"""scripts/bench_encoder.py on a tiny budget: every figure is measured and the last line printed is the JSON result."""

from __future__ import annotations

import json

import pytest


def test_bench_encoder_tiny(load_script, capsys):
    bench = load_script("bench_encoder")
    cfg = bench.Config(sizes=("tinier",), gpu_sizes=("tinier",), batch=1, iters=1, warmup=0, threads=1,
                       fusion_size="tinier", gpu=False)
    result = bench.run(cfg)
    out = capsys.readouterr().out.strip().splitlines()
    assert json.loads(out[-1]) == result
    assert result["params"] == {"tinier": 3_760_512} and result["gpu_ms"] is None
    for key in ("bottleneck_ms", "vanilla_ms", "bottleneck_over_vanilla", "tinier_4tips_ms",
                "tinier_4tips_preprocess_ms", "tinier_4tips_bf16_ms"):
        assert result[key] > 0, key
    assert result["cpu_ms"]["tinier"] > 0
    assert abs(result["bottleneck_over_vanilla"] - result["bottleneck_ms"] / result["vanilla_ms"]) < 1e-2
    assert any(line.startswith("tinier ") for line in out)  # the table
    with pytest.raises(ValueError, match="unknown size"):
        bench.run(bench.Config(sizes=("huge",)))
