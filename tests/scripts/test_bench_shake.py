"""scripts/bench_shake.py on a tiny budget: the real collector, the windows counted as the loader cuts them."""

from __future__ import annotations

import json

import pytest


def test_bench_shake_tiny(load_script, capsys):
    bench = load_script("bench_shake")
    assert bench.main(["--episodes", "1", "--shake-s", "1.3"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # 0.18 s after the first window's 1.12 s of history: a few 30 fps frames, each for the 4 fingertips
    assert 0 < result["windows"] <= 4 * 6 and result["windows"] % 4 == 0 and result["windows_per_s"] > 0
    assert sum(result["contents"].values()) == 1
    assert result["target_ratio"] == pytest.approx(result["minutes_per_1000_windows"] / 10, rel=1e-3)
    with pytest.raises(ValueError, match="shake_s"):
        bench.run(bench.Config(shake_s=1.0))
