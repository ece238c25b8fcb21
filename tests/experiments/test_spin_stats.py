"""experiments/tools/spin_stats.py: per-step spin of a policy, its clipped mean, and the histogram."""

from __future__ import annotations

import json

import numpy as np
import pytest


@pytest.fixture(scope="module")
def spin(load_script):
    return load_script("spin_stats")


def test_summary_of_a_ratchet(spin):
    cfg = spin.Config(rotate_clip=0.5, rotate_back_clip=0.5)
    r = spin.summarize(np.array([0.4] * 5 + [-2.0]), cfg)
    assert r["mean_spin"] == pytest.approx(0.0, abs=1e-4)
    assert r["mean_clipped"] == pytest.approx(1.5 / 6, abs=1e-4)  # what the symmetric clip pays for no rotation
    assert r["frac_below_back_clip"] == pytest.approx(1 / 6, abs=1e-4) and r["frac_above_clip"] == 0.0


def test_shipped_teacher_tiny_run(spin, tmp_path):
    out = tmp_path / "spin"
    assert spin.main(["--policies", "teacher", "t2=teacher", "--episodes", "2", "--episode-steps", "4",
                      "--out", str(out), "--no-progress"]) == 0
    result = json.loads((out / "spin.json").read_text())
    assert set(result) == {"teacher", "t2"} and result["teacher"] == result["t2"]  # same seeds, deterministic
    assert result["teacher"]["steps"] == 8
    assert (out / "spin.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_input(spin, tmp_path, capsys):
    assert spin.main(["--policies", "a=teacher", "a=student", "--out", str(tmp_path)]) == 2
    assert "share a name" in capsys.readouterr().err
    with pytest.raises(ValueError, match="episodes"):
        spin.run(spin.Config(episodes=0, out=tmp_path))
