"""scripts/bench_adapter.py on a tiny budget: the touch step runs from raw windows and the last line is the JSON."""

from __future__ import annotations

import json

import pytest


def test_bench_adapter_tiny(load_script, capsys):
    bench = load_script("bench_adapter")
    assert bench.main(["--iters", "1", "--threads", "1"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    figures = {"step_ms", "step_img_ms", "step_imu_pressure_ms", "student_ms", "amortized_ms", "touch_every"}
    assert figures <= set(result)
    assert result["step_ms"] > result["student_ms"] > 0 and result["step_imu_pressure_ms"] > 0
    assert result["touch_every"] == 4
    with pytest.raises(ValueError, match=">= 1"):
        bench.run(bench.Config(iters=0))
