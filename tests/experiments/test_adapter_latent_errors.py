"""experiments/tools/adapter_latent_errors.py: an adapter's latent error to the teacher's z, binned by friction, mass
and time into the episode."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from adapters.bundle import build_adapted


@pytest.fixture(scope="module")
def errors_script(load_script):
    return load_script("adapter_latent_errors")


def test_bins_split_the_samples_and_measure_each_latent_against_the_teachers(errors_script):
    teacher = np.zeros((4, 2), np.float32)
    student = np.array([[1, 0], [1, 0], [0, 2], [0, 2]], np.float32)
    adapted = np.array([[0, 0], [0, 0], [0, 1], [0, 1]], np.float32)
    samples = errors_script.Samples(student, adapted, teacher, friction=np.array([0.2, 0.5, 2.0, 2.5]),
                                    mass=np.zeros(4), time=np.zeros(4))
    low, high = errors_script.bin_table(samples, samples.friction, (0.75, 1.5))  # the middle bin is empty
    assert (low["low"], low["high"], low["samples"]) == (None, 0.75, 2)
    assert (high["low"], high["high"], high["samples"]) == (1.5, None, 2)
    assert low["mse_student"] == pytest.approx(0.5) and low["mse_adapted"] == 0.0
    assert high["mse_student"] == pytest.approx(2.0) and high["mse_adapted"] == pytest.approx(0.5)
    assert high["mean_adapted"] == [0.0, 1.0] and high["mean_teacher"] == [0.0, 0.0]
    assert "action_mse_student" not in low  # samples without actions: latent errors only


def test_bins_measure_the_actions_on_each_latent_against_the_action_on_the_teachers(errors_script):
    zeros = np.zeros((4, 2), np.float32)
    action_teacher = np.array([[0, 0, 0], [1, 1, 1], [0, 0, 0], [1, 1, 1]], np.float32)
    action_student = action_teacher + np.array([[3], [3], [1], [1]], np.float32)  # off by 3, then by 1
    action_adapted = action_teacher + np.array([[1], [1], [0], [0]], np.float32)
    samples = errors_script.Samples(zeros, zeros, zeros, friction=np.zeros(4), mass=np.array([0.1, 0.1, 0.3, 0.3]),
                                    time=np.zeros(4), action_student=action_student, action_adapted=action_adapted,
                                    action_teacher=action_teacher)
    light, heavy = errors_script.bin_table(samples, samples.mass, (0.2,))
    assert (light["action_mse_student"], light["action_mse_adapted"]) == (pytest.approx(9.0), pytest.approx(1.0))
    assert (heavy["action_mse_student"], heavy["action_mse_adapted"]) == (pytest.approx(1.0), 0.0)


def test_a_fresh_adapter_has_exactly_the_students_error_in_every_bin(errors_script, tmp_path):
    torch.manual_seed(0)
    adapter = build_adapted("student", "sparshx-tinier-sim", ("imu", "pressure"), touch_every=4)
    adapter.save(tmp_path / "adapter")
    out = tmp_path / "report"
    args = ["--adapter", str(tmp_path / "adapter"), "--condition", "friction_0.25", "--num-envs", "2", "--steps", "8",
            "--seed", "5", "--out", str(out), "--friction-edges", "0.3", "--time-edges", "0.1"]
    assert errors_script.main(args) == 0
    report = json.loads((out / "errors.json").read_text())
    assert report["total"]["samples"] == 2 * 2  # 2 envs x refreshes at steps 0 and 4
    assert sum(row["samples"] for row in report["friction"]) == 4
    assert sum(row["samples"] for row in report["mass"]) == 4
    # refreshes at 0 s and at 4 x 0.05 s = 0.2 s (no episode ends in 8 steps): two samples on each side of 0.1 s
    assert [(row["low"], row["high"], row["samples"]) for row in report["time"]] == [(None, 0.1, 2), (0.1, None, 2)]
    for row in report["friction"] + report["mass"] + report["time"]:
        assert row["mse_adapted"] == row["mse_student"] > 0.0  # zero correction: phi's own error
        assert row["mean_adapted"] == row["mean_student"]
        assert row["action_mse_adapted"] == row["action_mse_student"] > 0.0  # same latent, same action
    assert {(row["low"], row["high"]) for row in report["friction"]} <= {(None, 0.3), (0.3, None)}
    assert (out / "errors.png").stat().st_size > 0 and "| bin |" in (out / "errors.md").read_text()
    assert errors_script.main(args) == 2  # the report is kept, not overwritten


def test_a_bundle_without_touch_is_refused(errors_script, tmp_path, capsys):
    assert errors_script.main(["--adapter", "student", "--out", str(tmp_path / "r")]) == 2
    assert "not an adapter bundle" in capsys.readouterr().err
    # a real adapter (none ships while one is retrained on the current hand model: a fresh one) with a student given
    # as its teacher
    build_adapted("student", "sparshx-tinier-sim", ("pressure",)).save(tmp_path / "adapter")
    assert errors_script.main(["--adapter", str(tmp_path / "adapter"), "--teacher", "student", "--out",
                               str(tmp_path / "r")]) == 2
    assert "not a teacher bundle" in capsys.readouterr().err
    assert errors_script.main(["--friction-edges", "1.5", "0.75", "--out", str(tmp_path / "r")]) == 2
    assert "strictly increasing" in capsys.readouterr().err
