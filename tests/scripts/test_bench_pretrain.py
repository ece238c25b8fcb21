"""scripts/bench_pretrain.py on a tiny budget: every figure is measured and the last line printed is the JSON result."""

from __future__ import annotations

import json

import pytest


def test_bench_pretrain_tiny(load_script, capsys):
    bench = load_script("bench_pretrain")
    cfg = bench.Config(sessions=2, session_steps=30, workers=0, batch_size=4, batches=2, device="cpu", steps=2,
                       threads=1)
    result = bench.run(cfg)
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == result
    assert result["windows"] > 8
    for key in ("loader_windows_per_s_live", "cache_windows_per_s", "loader_windows_per_s", "pretrain_samples_per_s"):
        assert result[key] > 0, key
    with pytest.raises(ValueError, match="session_steps"):
        bench.run(bench.Config(session_steps=10))
