"""`rotate hand-info` against the emulated hands, and the deploy benchmark on a tiny budget."""

from __future__ import annotations

import json

from rotation.cli import main
from rotation.jobs.hand_info import Config, run


def test_hand_info_sim_allegro(capsys):
    run(Config(hand="sim-allegro"))
    out = capsys.readouterr().out
    assert "allegro-v4" in out and "0x0406" in out and "SAH040E1" in out
    assert "thumb_3" in out and out.count("\n") >= 16 + 5


def test_hand_info_sim_leap_through_the_cli(capsys):
    assert main(["hand-info", "--hand", "sim-leap"]) == 0
    out = capsys.readouterr().out
    assert "leap" in out and "XC330-M288 x16" in out and "index_0" in out


def test_bench_deploy_smoke(load_script, capsys):
    module = load_script("bench_deploy")
    result = module.run(module.Config(duration_s=0.5, warmup_s=0.2, rt_priority=0))
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(last) == result
    assert result["pd_hz"] > 0 and result["pd_jitter_p99_ms"] >= 0  # figures, not bounds: see the benchmark
