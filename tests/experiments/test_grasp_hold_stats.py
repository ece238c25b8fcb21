"""experiments/tools/grasp_hold_stats.py: the hold check of every grasp of a cache, its pass rate and the histogram."""

from __future__ import annotations

import json

import pytest

from envs.config import default_randomization
from envs.constants import DEFAULT_HAND
from envs.grasp_cache import GraspCache
from envs.grasps import HoldRule, generate_grasps, hold_check


@pytest.fixture(scope="module")
def stats(load_script):
    return load_script("grasp_hold_stats")


def test_pass_rate_of_a_cache_generated_without_the_rule(stats, tmp_path):
    """Grasps of the default hand at its nominal scale, checked with the rule `rotate grasps` uses on that hand (its
    nominal friction and mass, given to the script; its own defaults are HoldRule's, the first hand's)."""
    scales = default_randomization(DEFAULT_HAND).scales
    cache = generate_grasps("cup", (scales[len(scales) // 2],), per_scale=16, batch_size=16, seed=0, nthread=1)
    cache.save(tmp_path / "g.npz")
    out = tmp_path / "hold"
    rule = HoldRule.for_hand(DEFAULT_HAND)
    assert stats.main(["--caches", f"plain={tmp_path / 'g.npz'}", "--friction", str(rule.friction), "--mass",
                       str(rule.mass), "--out", str(out)]) == 0
    result = json.loads((out / "hold_stats.json").read_text())
    expected = (hold_check(GraspCache.load(tmp_path / "g.npz"), rule) < rule.max_tilt).mean()
    assert 0.0 < expected < 1.0  # this sample has grasps that fail
    assert result["caches"]["plain"]["pass"] == pytest.approx(expected, abs=1e-4)
    assert result["caches"]["plain"]["grasps"] == 16 and result["caches"]["plain"]["cache_hold_rule"] == []
    assert result["rule"] == list(rule.as_array())
    assert (out / "hold_tilt.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    slippery = tmp_path / "hold_slippery"  # a quarter of the cup surface's friction, domes and links together
    assert stats.main(["--caches", f"plain={tmp_path / 'g.npz'}", "--friction", str(rule.friction), "--mass",
                       str(rule.mass), "--surface", "0.25", "--out", str(slippery)]) == 0
    result = json.loads((slippery / "hold_stats.json").read_text())
    slippery_rule = HoldRule.for_hand(DEFAULT_HAND, surface=0.25)
    worst = hold_check(GraspCache.load(tmp_path / "g.npz"), slippery_rule)
    assert result["surface"] == 0.25 and result["caches"]["plain"]["surface"] == 0.25
    assert result["rule"] == list(slippery_rule.as_array())  # five numbers: the surface is recorded
    assert result["caches"]["plain"]["pass"] == pytest.approx((worst < rule.max_tilt).mean(), abs=1e-4)
    assert result["caches"]["plain"]["pass"] < expected


def test_bad_input_is_one_line(stats, tmp_path, capsys):
    assert stats.main(["--caches", f"x={tmp_path / 'nope.npz'}", "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert stats.main(["--caches", "=cup", "--out", str(tmp_path / "o")]) == 2
    assert stats.main(["--seconds", "0", "--out", str(tmp_path / "o")]) == 2
    assert stats.main(["--surface", "0", "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
