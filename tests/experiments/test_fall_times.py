"""experiments/tools/fall_times.py: fall times of evaluations, counted by hand, and the schema of a real evaluation."""

from __future__ import annotations

import json

import pytest


@pytest.fixture(scope="module")
def falls(load_script):
    return load_script("fall_times")


def _write_run(folder, rows):
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({"rows": rows, "config": {}}))


def _row(policy, condition, ttf, in_hand):
    return {"policy": policy, "condition": condition, "per_episode": {"ttf": ttf, "in_hand_time": in_hand}}


def test_figures_counted_by_hand(falls, tmp_path):
    """Four 20 s episodes: two held, one lost at 1 s (early), one at 10 s."""
    _write_run(tmp_path / "a", [_row("teacher", "friction_0.25", [1.0, 0.05, 0.5, 1.0], [20.0, 1.0, 10.0, 20.0]),
                                _row("teacher", "nominal", [1.0, 1.0], [20.0, 20.0])])
    _write_run(tmp_path / "b", [_row("teacher", "friction_0.25", [0.025, 0.05], [0.5, 1.0])])
    out = tmp_path / "out"
    assert falls.main(["--runs", f"old={tmp_path / 'a'}", f"new={tmp_path / 'b'}", "--out", str(out)]) == 0
    result = json.loads((out / "fall_times.json").read_text())
    slippery = result["conditions"]["friction_0.25"]
    assert slippery["old/teacher"] == {"episodes": 4, "fell": 2, "fell_early": 1, "held": 2, "ttf": 0.6375,
                                       "median_fall_s": 5.5}
    assert slippery["new/teacher"]["fell_early"] == 2 and slippery["new/teacher"]["held"] == 0
    assert result["conditions"]["nominal"]["old/teacher"]["median_fall_s"] is None
    assert (out / "survival.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert falls.main(["--runs", str(tmp_path / "a"), "--early", "0.5", "--out", str(tmp_path / "o2")]) == 0
    one = json.loads((tmp_path / "o2" / "fall_times.json").read_text())["conditions"]["friction_0.25"]
    assert set(one) == {"teacher"} and one["teacher"]["fell_early"] == 0


def test_reads_a_real_evaluation(falls, tmp_path):
    from rotation.cli import main

    run = tmp_path / "eval"
    assert main(["evaluate", "--policy", "teacher", "--conditions", "friction_0.25", "--episodes", "2",
                 "--num-envs", "2", "--episode-steps", "10", "--seed", "5", "--out", str(run), "--no-progress"]) == 0
    assert falls.main(["--runs", str(run), "--out", str(tmp_path / "f")]) == 0
    stats = json.loads((tmp_path / "f" / "fall_times.json").read_text())["conditions"]["friction_0.25"]["teacher"]
    assert stats["episodes"] == 2 and stats["fell"] + stats["held"] == 2


def test_bad_input_is_one_line(falls, tmp_path, capsys):
    assert falls.main(["--runs", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "results.json").write_text(json.dumps({"rows": [{"policy": "x"}]}))
    assert falls.main(["--runs", str(tmp_path / "bad"), "--out", str(tmp_path / "o")]) == 2
    assert "no per-episode" in capsys.readouterr().err
    assert falls.main(["--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
