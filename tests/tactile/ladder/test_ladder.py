"""`rotate touch-report`: the ladder's readers, stage 1 on a scripted sliding finger, and a tiny run end to end."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest
import torch

from envs.sensors import digit360_model as M
from envs.sensors.digit360 import FINGERS, Digit360Readout, add_digit360_sensors
from rotation.cli import main
from rotation.jobs import collect
from rotation.tactile.ladder import fit
from rotation.tactile.ladder import job as ladder
from rotation.tactile.ladder.encode import pool
from rotation.tactile.ladder.samples import (
    CONTACT_FEATURES,
    SESSION_TARGETS,
    SLIP_FLOOR,
    _track_features,
    finger_columns,
    history_mean,
    slip_history,
)
from rotation.tactile.models.encoders import ENCODERS
from rotation.tactile.models.sparshx import SparshX, SparshXConfig

SLIDE_XML = """
<mujoco>
  <option timestep="0.002" cone="elliptic" impratio="10"/>
  <worldbody>
    <geom type="box" size="0.3 0.05 0.005" pos="0 0 -0.005" friction="{mu} 0.005 0.0001"/>
    <body pos="0 0 0.012">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="z" type="slide" axis="0 0 1"/>
      <geom name="index_tip" type="sphere" size="0.012" mass="0.03" friction="{mu} 0.005 0.0001"/>
      <site name="index_tip" euler="180 0 0"/>
    </body>
    {others}
  </worldbody>
  <actuator>
    <position joint="x" kp="300" kv="10"/>
    <position joint="z" kp="300" kv="10"/>
  </actuator>
</mujoco>"""


def sliding_finger(mu: float, press: float, speed: float, seconds: float = 3.5) -> np.ndarray:
    """Contact-field rows (every 2 ms) of a Digit 360 dome pressed ``press`` m into a plate of friction ``mu`` and
    dragged along it at ``speed`` m/s after 0.5 s (MuJoCo, elliptic cones)."""
    others = "".join(f'<body pos="{0.3 + 0.05 * i} 0.3 0.3"><geom name="{f}_tip" type="sphere" size="0.012" '
                     f'contype="0" conaffinity="0"/><site name="{f}_tip"/></body>' for i, f in enumerate(FINGERS[1:]))
    spec = mujoco.MjSpec.from_string(SLIDE_XML.format(mu=mu, others=others))
    add_digit360_sensors(spec, history=1)
    model = spec.compile()
    data = mujoco.MjData(model)
    readout = Digit360Readout(model)
    rows = []
    for k in range(int(seconds / model.opt.timestep)):
        t = k * model.opt.timestep
        data.ctrl[:] = (0.0 if t < 0.5 else speed * (t - 0.5), -press)
        mujoco.mj_step(model, data)
        rows.append(readout.read_current(data.sensordata[None])[0, 0, 0])
    return np.stack(rows)


def test_stage1_reads_friction_from_a_scripted_sliding_finger():
    """While a contact slides its shear-to-normal ratio is the friction coefficient: the ladder's first rung reads
    friction on sliding windows of coefficients it never trained on, whatever the press and the speed."""
    rng = np.random.default_rng(0)
    mus = np.linspace(0.3, 1.2, 10)
    feats, target, groups = [], [], []
    ratio = 3 + 3 + 3  # index of ratio_sliding in _track_features: after the stats of fn, ft and slip
    assert CONTACT_FEATURES[3] == "ratio_sliding"
    for g, mu in enumerate(mus):
        rows = sliding_finger(mu, press=rng.uniform(0.003, 0.008), speed=rng.uniform(0.01, 0.04))
        for start in range(750, len(rows) - 150, 150):  # 0.3 s windows once sliding (the drag pulls it loose first)
            f = _track_features(rows[start:start + 150])
            assert f[ratio] == pytest.approx(mu, rel=0.05)
            feats.append(f)
            target.append([mu])
            groups.append(g)
    x, y, groups = np.asarray(feats), np.asarray(target), np.asarray(groups)
    test = np.isin(groups, [1, 5, 8])
    r2, _ = fit.fit_and_score("r2", x[~test], y[~test], groups[~test], x[test], y[test])
    assert r2 > 0.95


def test_readers_read_what_is_there_and_nothing_else():
    rng = np.random.default_rng(1)
    groups = np.repeat(np.arange(12), 30)
    signal = rng.normal(size=(len(groups), 1))
    noise = rng.normal(size=(len(groups), 20))
    y = 2.0 * signal + 0.1 * rng.normal(size=signal.shape)
    test = groups >= 9
    with_signal, _ = fit.fit_and_score("r2", np.hstack([signal, noise])[~test], y[~test], groups[~test],
                                       np.hstack([signal, noise])[test], y[test])
    without, _ = fit.fit_and_score("r2", noise[~test], y[~test], groups[~test], noise[test], y[test])
    assert with_signal > 0.95 and without < 0.1
    # a rare binary event that a feature crosses a cut of: the F1 reader finds the cut, not 0.5
    speed = rng.exponential(0.002, size=(len(groups), 4))
    slip = (speed > 0.005).astype(float)
    f1, _ = fit.fit_and_score("f1", speed[~test], slip[~test], groups[~test], speed[test], slip[test])
    assert 0.02 < slip.mean() < 0.2 and f1 > 0.8
    assert fit.chance("f1", slip[test]) < 0.4 and fit.chance("r2", y[test]) == 0.0
    # nested budgets
    small, large = fit.budget_sessions(np.arange(9), 0.33, 0), fit.budget_sessions(np.arange(9), 1.0, 0)
    assert len(small) == 3 and set(small) <= set(large) and len(large) == 9


def test_history_mean_averages_a_session_s_past_and_nothing_later():
    # two sessions, shuffled; frames 15 apart (0.5 s at 30 fps): a 1 s history holds this window and the one before
    session = np.array([1, 0, 0, 1, 0, 0, 1])
    frame = np.array([15, 45, 0, 0, 30, 15, 30])
    values = np.array([[20.0], [4.0], [1.0], [10.0], [3.0], [2.0], [30.0]])
    got = history_mean(values, session, frame, 1.0)[:, 0]
    np.testing.assert_allclose(got, [15.0, 3.5, 1.0, 10.0, 2.5, 1.5, 25.0])
    assert history_mean(values, session, frame, 10.0)[1, 0] == pytest.approx(2.5)  # the whole past of session 0
    np.testing.assert_array_equal(history_mean(values, session, frame, 0.0), values)
    later = values.copy()
    later[1] = 100.0  # session 0's last window changes: no earlier moment's reading moves
    np.testing.assert_array_equal(history_mean(later, session, frame, 1.0)[[2, 4, 5]],
                                  history_mean(values, session, frame, 1.0)[[2, 4, 5]])
    assert set(SESSION_TARGETS) == {"friction_tercile", "friction", "mass", "com"}


def test_slip_history_counts_each_fingertip_s_sliding_windows_most():
    # one session, three windows 0.5 s apart; two blocks of features, each the four fingertips' columns side by side
    finger = finger_columns([4, 8])
    np.testing.assert_array_equal(finger, [0, 1, 2, 3, 0, 0, 1, 1, 2, 2, 3, 3])
    session, frame = np.zeros(3, int), np.array([0, 15, 30])
    values = np.tile(np.array([[1.0], [2.0], [4.0]]), (1, 12))
    weights = np.zeros((3, 4))
    weights[:, 0] = [1.0, 0.0, 1.0]  # fingertip 0 slides in the first and last window
    weights[:, 1] = [0.0, 1.0, 0.0]  # fingertip 1 in the middle one; 2 and 3 never (the floor: a plain mean)
    got = slip_history(values, finger, weights, session, frame, 10.0)
    f = SLIP_FLOOR
    np.testing.assert_allclose(got[2, finger == 0], (1 * 1 + 2 * f + 4 * 1) / (2 + f))
    np.testing.assert_allclose(got[2, finger == 1], (1 * f + 2 * 1 + 4 * f) / (1 + 2 * f))
    np.testing.assert_allclose(got[2, finger >= 2], 7 / 3)
    np.testing.assert_allclose(got[1, finger == 0], (1 + 2 * f) / (1 + f))  # causal: the last window is not seen
    np.testing.assert_array_equal(slip_history(values, finger, weights, session, frame, 0.0), values)
    with pytest.raises(ValueError, match="fingertips"):
        finger_columns([6])


def test_the_tercile_is_the_cut_of_the_friction_estimate():
    edges = np.array([0.6, 0.9])
    got = fit.tercile_of(np.array([[0.1], [0.6], [0.75], [0.9], [2.0]]), edges)
    np.testing.assert_array_equal(got[:, 0], [0, 1, 1, 2, 2])  # the targets' own rule: searchsorted, right


def test_a_score_s_error_resamples_whole_sessions():
    # two sessions of 500 moments: every moment of the first read right, every one of the second wrong
    groups = np.repeat([3, 7], 500)
    y = np.zeros((1000, 1))
    pred = np.concatenate([np.zeros(500), np.ones(500)])[:, None]
    # two sessions drawn with replacement score 1, 0.5 or 0 (chances 1/4, 1/2, 1/4): a spread of sqrt(1/8); moments
    # resampled one by one would give about 0.016
    assert fit.session_error("accuracy", pred, y, groups) == pytest.approx(np.sqrt(1 / 8), abs=0.05)
    assert fit.session_error("accuracy", y, y, groups) == 0.0
    assert np.isnan(fit.session_error("accuracy", pred, y, np.zeros(1000)))


def test_pooled_tokens_keep_what_a_single_token_carries():
    torch.manual_seed(0)
    tokens = torch.randn(2, 196, 64)
    tokens[1, 17, 3] += 50.0  # one patch of the second window carries a strong feature
    pooled = pool(tokens)
    normed = torch.nn.functional.layer_norm(tokens, (64,))
    assert pooled.shape == (2, 128)
    torch.testing.assert_close(pooled[:, :64], normed.mean(1))
    torch.testing.assert_close(pooled[:, 64:], normed.amax(1))
    # the mean barely tells the two windows apart on that channel; the maximum does
    gap_max, gap_mean = float(pooled[1, 64 + 3] - pooled[0, 64 + 3]), abs(float(pooled[1, 3] - pooled[0, 3]))
    assert gap_max > 3.0 and gap_max > 20 * gap_mean


@pytest.fixture(scope="module")
def v4_sessions(tmp_path_factory):
    """Four short sessions on the vendor-kinematics hand (generation-2 touch), gentle random actions."""
    out = tmp_path_factory.mktemp("v4_touch")
    collect.run(collect.Config(out=out, episodes=4, num_envs=4, episode_steps=40, seed=3, random_scale=0.15,
                               hand="digit360_v4", progress=False))
    return out


@pytest.fixture(scope="module")
def encoder(tmp_path_factory):
    """An untrained tinier Sparsh-X on all four modalities, saved as `rotate pretrain` exports encoders."""
    torch.manual_seed(0)
    model = SparshX(SparshXConfig(size="tinier"))
    return ENCODERS["sparshx"].save(model, tmp_path_factory.mktemp("enc") / "encoder.safetensors")


def test_collect_on_the_vendor_hand_records_its_sensor(v4_sessions):
    from rotation.data.dataset import TouchWindows, find_sessions
    from rotation.data.session_reader import SessionReader

    paths = find_sessions(v4_sessions)
    with SessionReader(paths[0]) as r:
        assert r.meta.extra["sim_hand"] == "digit360_v4" and r.meta.extra["touch_generation"] == 2
    assert TouchWindows(paths[:1]).sensor_model(0) == M.CONTACT_MODEL


def test_a_tiny_touch_report_runs_end_to_end(tmp_path, v4_sessions, encoder):
    out = tmp_path / "report"
    argv = ["touch-report", "--sessions", str(v4_sessions), "--checkpoint", str(encoder), "--out", str(out),
            "--stride", "10", "--e2e-steps", "1", "--e2e-batch", "1", "--test-fraction", "0.5", "--friction-reading",
            "slip", "--no-progress"]
    assert main(argv) == 0
    result = json.loads((out / "results.json").read_text())
    assert result["complete"] and result["samples"] > 0 and result["history"] == 5.0
    assert result["friction_reading"] == "slip"
    assert "the last 5 s" in (out / "results.md").read_text() and "sliding" in (out / "results.md").read_text()
    seen = {(r["stage"], r["features"]) for r in result["rows"]}
    assert {("contact", "fields"), ("streams", "all"), ("streams", "image"), ("tokens", "all"), ("tokens", "audio"),
            ("e2e", "all")} <= seen
    assert {r["target"] for r in result["rows"]} == {"friction_tercile", "friction", "mass", "com", "normal_force",
                                                      "slip"}
    assert all(np.isfinite(r["value"]) or r["metric"] == "r2" for r in result["rows"])
    assert all("se" in r for r in result["rows"]) and " ± " in (out / "results.md").read_text()
    assert any(c["check"].startswith("friction tercile") for c in result["checks"])
    for name in ("results.md", "ladder.png", "budgets.png", "frames.png", "features_contact.npz",
                 "features_rendered.npz"):
        assert (out / name).is_file(), name
    before = (out / "features_rendered.npz").stat().st_mtime_ns
    assert main([*argv[:-9], "--friction-reading", "slip", "--stages", "1", "2", "--no-progress"]) == 0  # reuses
    assert (out / "features_rendered.npz").stat().st_mtime_ns == before
    fresh = tmp_path / "fresh"  # features without tokens are not reused by a run that needs them
    again = ["touch-report", "--sessions", str(v4_sessions), "--checkpoint", str(encoder), "--out", str(fresh),
             "--stride", "20", "--no-progress", "--stages"]
    assert main([*again, "2"]) == 0
    assert not any(k.startswith("tokens/") for k in np.load(fresh / "features_rendered.npz").files)
    assert main([*again, "3"]) == 0
    assert any(k.startswith("tokens/") for k in np.load(fresh / "features_rendered.npz").files)


def test_bad_input_is_a_clear_error(tmp_path, v4_sessions, capsys):
    with pytest.raises(ValueError, match="--checkpoint"):
        ladder.Config(sessions=(v4_sessions,), out=tmp_path / "r", checkpoint=None)  # stages 3, 4 need an encoder
    with pytest.raises(ValueError, match="stages"):
        ladder.Config(sessions=(v4_sessions,), out=tmp_path / "r", stages=(5,))
    one, two = sorted(v4_sessions.rglob("*.h5"))[:2]
    out = tmp_path / "mine"
    assert main(["touch-report", "--sessions", str(one), str(two), "--stages", "1", "--out", str(out),
                 "--no-progress"]) == 0
    before = (out / "results.json").read_bytes()
    assert main(["touch-report", "--sessions", str(v4_sessions), "--stages", "1", "--out", str(out)]) == 1
    assert "holds the report of other sessions" in capsys.readouterr().err
    assert (out / "results.json").read_bytes() == before  # kept
    assert main(["touch-report", "--sessions", str(one), str(two), "--stages", "1", "--history", "0", "--out",
                 str(out)]) == 1  # the same sessions read another way: not written over the first reading
    assert "history" in capsys.readouterr().err
    assert main(["touch-report", "--sessions", str(one), str(two), "--stages", "1", "--friction-reading", "slip",
                 "--out", str(out)]) == 1  # nor with the other friction reading
    assert "friction reading" in capsys.readouterr().err
    assert (out / "results.json").read_bytes() == before
    assert json.loads(before)["friction_reading"] == "mean"  # the default
    assert "classifier of its own" in (out / "results.md").read_text()
    assert main(["touch-report", "--sessions", str(one), "--stages", "1", "--out", str(tmp_path / "r")]) == 1
    assert "at least 2 session files" in capsys.readouterr().err
    with pytest.raises(ValueError, match="history"):
        ladder.Config(sessions=(v4_sessions,), out=tmp_path / "r", stages=(1,), history=-1.0)
    with pytest.raises(ValueError, match="friction_reading"):
        ladder.Config(sessions=(v4_sessions,), out=tmp_path / "r", stages=(1,), friction_reading="max")
