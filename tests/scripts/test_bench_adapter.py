"""scripts/bench_adapter.py on a tiny budget: the touch step runs from raw windows and the last line is the JSON."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bench_adapter.py"


def load_script():
    spec = importlib.util.spec_from_file_location("bench_adapter", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is created
    spec.loader.exec_module(module)
    return module


def test_bench_adapter_tiny(capsys):
    bench = load_script()
    assert bench.main(["--iters", "1", "--threads", "1"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {"step_ms", "step_img_ms", "student_ms", "amortized_ms", "touch_every"} <= set(result)
    assert result["step_ms"] > result["student_ms"] > 0 and result["touch_every"] == 8
    with pytest.raises(ValueError, match=">= 1"):
        bench.run(bench.Config(iters=0))
