"""experiments/tools/insertion_rounds.py: the prong's movement in the hand and the outcomes, counted by hand on
episodes written field by field, and read from a real recorded demonstration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter


@pytest.fixture(scope="module")
def rounds(load_script):
    return load_script("insertion_rounds")


def _write(path, wrist, prong, force, **props):
    """A session in the demonstrations' format with just the streams the tool reads, at 20 Hz."""
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = SessionMeta(source="sim", object="plug", control_hz=20.0, seed=0,
                       properties={"success": False, "lost": False, "slipped": False, **props})
    streams = {"wrist/pose": wrist, "labels/prong": prong, "labels/socket_force": force}
    with SessionWriter(path, meta, [StreamSetup(k, rate_hz=20.0) for k in streams]) as w:
        for key, value in streams.items():
            w.append(key, np.asarray(value, dtype=np.float32), np.arange(len(value)) / 20.0)


def test_in_wrist_turns_into_the_wrists_frame(rounds):
    c = math.cos(math.pi / 4)
    wrist = np.array([[0.1, 0.2, 0.3, c, 0.0, 0.0, c]])  # 90 degrees about z
    prong = np.array([[0.11, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]])  # 1 cm along world x
    assert rounds.in_wrist(wrist, prong) == pytest.approx(np.array([[0.0, -0.01, 0.0]]), abs=1e-7)


def test_figures_counted_by_hand(rounds, tmp_path):
    """Episode A: the wrist rises 1 mm a step with the prong 3 cm above it until step 3, where the prong drops 6 mm in
    the hand and stays there (5 steps: 2 of them moved > 5 mm); the socket pushes 2 N from step 2, 9 N at step 3.
    Episode B: nothing moves, seated with 1 N."""
    ident = [1.0, 0.0, 0.0, 0.0]
    wrist = [[0.0, 0.0, 0.001 * i, *ident] for i in range(5)]
    prong = [[0.0, 0.0, 0.001 * i + 0.03 - (0.006 if i >= 3 else 0.0), *ident] for i in range(5)]
    _write(tmp_path / "shard_000" / "episode_000000.h5", wrist, prong, [[0], [0], [2], [9], [3]], slipped=True)
    _write(tmp_path / "shard_000" / "episode_000001.h5", wrist[:3], [[0, 0, 0.03, *ident]] * 3, [[0], [1], [1]],
           success=True)
    lines = rounds.summary(tmp_path, 0.005)
    assert lines[0].endswith("2 episodes, 8 steps; prong moved > 5 mm in the hand in 25.0% of the steps and in 1 "
                             "episodes")
    assert lines[1] == ("  those episodes: first such step median 3; touched the socket before it in 1; largest "
                        "socket force up to it median 9.0 N")
    assert lines[2] == "  seated: 1; median length 3 steps, largest socket force median 1.0 N"
    assert lines[3] == "  slipped: 1; median length 5 steps, largest socket force median 9.0 N"


def test_reads_a_recorded_demonstration(rounds, tmp_path, capsys):
    from rotation.cli import main

    out = tmp_path / "demos"
    assert main(["demos", "--task", "insertion", "--episodes", "1", "--seed", "3", "--out", str(out),
                 "--no-progress"]) == 0
    capsys.readouterr()
    assert rounds.main([str(out)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"{out}: 1 episodes,") and "seated: 1;" in text
    with pytest.raises(SystemExit, match="no episodes"):
        rounds.main([str(tmp_path / "empty")])
