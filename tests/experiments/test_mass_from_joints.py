"""experiments/tools/mass_from_joints.py: what the joints' tracking and the student's phi say about the cup's mass."""

from __future__ import annotations

import json

import numpy as np
import pytest

from envs.config import MAX_OBJECT_MASS, default_randomization
from rotation.bundles import load_bundle, policy_hand


@pytest.fixture(scope="module")
def script(load_script):
    return load_script("mass_from_joints")


def test_ridge_recovers_a_linear_target_on_held_out_rows_and_r2_scores_it(script):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 5)) * [1.0, 10.0, 0.1, 1.0, 1.0]
    y = 2.0 * x[:, 0] - 0.3 * x[:, 1] + 5.0 * x[:, 2] + 7.0
    train = np.arange(400) % 2 == 0
    pred = script.ridge_fit_predict(x, y, train, 1e-6)
    assert script.r2(pred[~train], y[~train]) > 0.9999
    assert script.r2(np.full(200, y[~train].mean()), y[~train]) == pytest.approx(0.0)
    noise = script.ridge_fit_predict(rng.normal(size=(400, 5)), y, train, 1e-2)  # features unrelated to y
    assert script.r2(noise[~train], y[~train]) < 0.05


def test_separation_is_in_nominal_episode_standard_deviations(script):
    episode = np.array([0, 0, 1, 1, 2, 2, 0, 1, 2])
    heavy = np.array([False] * 6 + [True] * 3)
    pred = np.array([1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0, 4.0])  # nominal episode means 1, 2, 3 (sd 1)
    assert script.separation(pred, episode, heavy) == pytest.approx(2.0)


def test_a_short_run_compares_every_feature_set_for_every_target(script, capsys):
    # the episodes run on the student's hand: 0.2 kg more where its randomization leaves room for it (the first
    # hand's 0.25 kg cups), else what it leaves (0.1 kg on digit360_v4's 0.4 kg mugs)
    hand = policy_hand(load_bundle("student"))
    added = round(min(0.2, MAX_OBJECT_MASS - default_randomization(hand).mass[1]), 3)
    assert added > 0
    assert script.main(["--envs", "4", "--steps", "48", "--warmup", "40", "--every", "4", "--dims", "2", "4",
                        "--added-mass", str(added)]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(out["result"]) == {"mass", "teacher z[2]", "teacher z[4]"}
    for row in out["result"].values():
        assert set(row) == {"phi", "tracking", "phi+tracking"}
        assert all(np.isfinite(v["r2"]) and v["r2"] <= 1.0 for v in row.values())


@pytest.mark.parametrize("args, message", [
    (["--envs", "1"], "--envs"), (["--warmup", "300"], "--warmup"), (["--every", "0"], "--every"),
    (["--added-mass", "0.5"], "--added-mass"), (["--ridge", "0"], "--ridge"), (["--dims", "8"], "--dims"),
    (["--student", "teacher"], "--student teacher"),
])
def test_bad_settings_are_one_line_errors(script, capsys, args, message):
    assert script.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
