"""scripts/delay_sweep.py on a tiny budget: the student and teacher once, the adapter at each delay, one table."""

from __future__ import annotations

import json


def test_delay_sweep_tiny(load_script, tmp_path):
    from adapters.bundle import build_adapted

    sweep = load_script("delay_sweep")
    adapter = tmp_path / "pressure"
    build_adapted("student", "sparshx-tinier-sim", ("pressure",), touch_every=2).save(adapter)
    out = tmp_path / "sweep"
    cfg = sweep.Config(adapter=str(adapter), delays=("0", "3"), conditions=("nominal", "friction_0.25"),
                       episodes=2, num_envs=2, episode_steps=30, out=out, progress=False)
    report = sweep.sweep(cfg)
    table = report["conditions"]
    assert set(table) == {"nominal", "friction_0.25"}
    for entry in table.values():
        assert set(entry["delays"]) == {"0", "3"} and 0 <= entry["student"][0] <= 1
        # a fresh adapter's correction is zero: at any delay it acts exactly as its student
        assert entry["delays"]["0"]["ttf"] == entry["delays"]["3"]["ttf"] == entry["student"][0]
    assert json.loads((out / "delay_sweep.json").read_text())["episodes"] == 2
    assert "adapter, delay 3" in (out / "delay_sweep.md").read_text() and (out / "delay_sweep.png").stat().st_size
    # the runs are kept: the same sweep again continues (nothing to run) and gives the same table
    again = sweep.sweep(cfg)["conditions"]
    assert json.loads(json.dumps(again)) == json.loads(json.dumps(table))
