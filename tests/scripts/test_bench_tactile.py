"""scripts/bench_tactile.py on a tiny budget: every rate measured, the last line is the JSON result."""

from __future__ import annotations

import json


def test_bench_tactile_tiny(load_script, capsys):
    bench = load_script("bench_tactile")
    argv = ["--num-envs", "2", "--env-steps", "16", "--rounds", "1", "--collect-steps", "40", "--reader-windows", "2",
            "--nthread", "1"]
    assert bench.main(argv) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {"tactile_over_plain", "reader_windows_per_s", "collect_samples_per_s", "obs_windows_per_s"} <= set(result)
    assert result["tactile_over_plain"] > 0 and result["reader_windows_per_s"] > 0
