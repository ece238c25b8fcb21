"""experiments/tools/insertion_touch_probe.py: the prong's offset in the socket's frame and the forces' change since
contact, read from an episode written field by field; the grouped ridge reader and the direction score on data whose
answers are known."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from envs.sensors.digit360 import FIELD, FINGERS, NUM_FIELDS
from rotation.data.session import SessionMeta, StreamSetup
from rotation.data.session_writer import SessionWriter


@pytest.fixture(scope="module")
def probe(load_script):
    return load_script("insertion_touch_probe")


def test_quat_mat_is_mujocos(probe):
    q = np.array([0.3, -0.5, 0.7, 0.2])
    want = np.zeros(9)
    mujoco.mju_quat2Mat(want, q / np.linalg.norm(q))
    assert probe.quat_mat(q) == pytest.approx(want.reshape(3, 3), abs=1e-12)


def test_an_episode_written_field_by_field(probe, tmp_path):
    """Socket turned 90 degrees about z at (0.1, 0, 0.2); the prong tip 2 mm along world x and 1 mm along world y from
    it, so (1, -2) mm in the socket's frame (its x is world y). The index dome's normal force is 0.8 N at step 0, 1 N
    at rest, 1.3 N while the socket presses (steps 2-3, after step 1 without contact), back to 1 N after: its change
    is counted from step 1, not from the episode's start."""
    c = math.cos(math.pi / 4)
    n = 5
    socket = np.tile([0.1, 0.0, 0.2, c, 0.0, 0.0, c], (n, 1))
    prong = np.tile([0.102, 0.001, 0.2, 1.0, 0.0, 0.0, 0.0], (n, 1))
    force = np.array([[0.0], [0.05], [2.0], [3.0], [0.0]])
    contact = np.zeros((n * 5, NUM_FIELDS), np.float32)  # 100 Hz rows, 5 per step
    contact[:, FIELD["force_n"]] = 1.0
    contact[0:5, FIELD["force_n"]] = 0.8  # step 0: the grip still settling
    contact[10:20, FIELD["force_n"]] = 1.3  # the rows of steps 2 and 3
    streams = {"actions/wrist": np.zeros((n, 6)), "labels/socket": socket, "labels/prong": prong,
               "labels/socket_force": force, "labels/depth": np.full((n, 1), -0.0005),
               "wrist/pose": np.zeros((n, 7)), "joints/position": np.zeros((n, 16))}
    meta = SessionMeta(source="sim", object="plug", control_hz=20.0, seed=0, properties={})
    setups = [StreamSetup(k, rate_hz=20.0) for k in streams] + [
        StreamSetup(f"digit360/{f}/contact", rate_hz=100.0) for f in FINGERS]
    path = tmp_path / "episode.h5"
    with SessionWriter(path, meta, setups) as w:
        for key, value in streams.items():
            w.append(key, np.asarray(value, dtype=np.float64), np.arange(n) / 20.0)
        for f in FINGERS:
            rows = contact if f == "index" else np.zeros_like(contact)
            w.append(f"digit360/{f}/contact", rows, np.arange(n * 5) / 100.0)
    e = probe.episode(path)
    assert e["offset_mm"][:, :2] == pytest.approx(np.tile([1.0, -2.0], (n, 1)), abs=1e-4)  # float32 storage
    assert e["offset_mm"][:, 2] == pytest.approx(np.zeros(n), abs=1e-4)
    assert e["forces"][:, 0] == pytest.approx([0.8, 1.0, 1.3, 1.3, 1.0], abs=1e-6)  # index normal force
    # its change since the last step below 0.1 N of socket force (step 1 for steps 2-3; itself otherwise)
    assert e["forces"][:, 12] == pytest.approx([0.0, 0.0, 0.3, 0.3, 0.0], abs=1e-6)


def test_the_ridge_reader_is_grouped_and_scores_directions(probe):
    rng = np.random.default_rng(0)
    groups = np.repeat(np.arange(40), 10)
    x = rng.normal(size=(400, 6))
    w = rng.normal(size=(6, 2))
    y = x @ w + 0.05 * rng.normal(size=(400, 2))
    p = probe.ridge_cv(x, y, groups, 1e-3)
    mean_r2, r2, direction = probe.scores(p, y, np.ones(400, bool))
    assert r2.min() > 0.95 and direction > 0.95
    noise = rng.normal(size=(400, 2))
    assert probe.scores(probe.ridge_cv(x, noise, groups, 1e-3), noise, np.ones(400, bool))[0] < 0.05
    # the direction score counts predictions within 45 degrees: one of these two is
    truth = np.array([[1.0, 0.0], [0.0, 1.0]])
    guess = np.array([[1.0, 0.9], [1.0, 0.2]])
    assert probe.scores(guess, truth, np.ones(2, bool))[2] == pytest.approx(0.5)
