"""TouchWindows: contract shapes, causality, determinism, recorded sessions, and the split by session."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.constants import FINGERS
from envs.sensors.digit360 import FIELD, NUM_FIELDS
from rotation.data.dataset import TouchWindows, split_sessions
from rotation.data.session import SessionError, SessionMeta, StreamSetup
from rotation.data.session_reader import SessionReader
from rotation.data.session_writer import SessionWriter

DT = 0.01


def contact_rows(times: np.ndarray, finger: int, wild_after: float = np.inf) -> np.ndarray:
    """Scripted contact fields: a press on the dome from 0.4 s (force ramp), sliding from 1.0 s; after
    ``wild_after`` s a different, violent history (impacts, strong slip)."""
    rows = np.zeros((len(times), NUM_FIELDS), np.float32)
    rows[:, FIELD["acc_z"]] = 9.81
    on = times >= 0.4
    theta = np.deg2rad(30 + 15 * finger)
    fn = np.clip((times - 0.4) * 4.0, 0.2, 2.0)
    wild = times > wild_after
    fn = np.where(wild, 6.0 * (np.arange(len(times)) % 3 == 0), fn)
    rows[on, FIELD["c0_found"]] = 1.0
    rows[on, FIELD["c0_fn"]] = fn[on]
    rows[on, FIELD["c0_x"]] = 0.014 * np.sin(theta)
    rows[on, FIELD["c0_z"]] = 0.014 * np.cos(theta)
    rows[on, FIELD["force_n"]] = fn[on] * np.cos(theta)
    rows[on, FIELD["force_x"]] = -fn[on] * np.sin(theta)
    rows[times >= 1.0, FIELD["c0_slip"]] = np.where(wild[times >= 1.0], 0.3, 0.02)
    rows[wild, FIELD["acc_x"]] = 30.0
    return rows


def write_sim_session(path, duration=2.0, key=1234, wild_after=np.inf, labels=True):
    times = np.arange(int(round(duration / DT))) * DT
    steps = np.arange(int(round(duration * 20)) + 1) / 20.0
    streams = [StreamSetup(f"digit360/{f}/contact", rate_hz=1 / DT) for f in FINGERS]
    if labels:
        streams += [StreamSetup("labels/force", rate_hz=20.0), StreamSetup("labels/priv", rate_hz=20.0)]
    meta = SessionMeta(source="sim", object="cylinder", control_hz=20.0, seed=0, extra={"touch_key": key})
    with SessionWriter(path, meta, streams) as w:
        for f, finger in enumerate(FINGERS):
            w.append(f"digit360/{finger}/contact", contact_rows(times, f, wild_after), times)
        if labels:
            force = np.tile(np.arange(len(steps), dtype=np.float32)[:, None, None], (1, 4, 3))  # value = step index
            w.append("labels/force", force, steps)
            w.append("labels/priv", np.zeros((len(steps), 9), np.float32), steps)
    return path


def write_real_session(path, duration=2.0, garbage_after=np.inf, image_hw=(240, 320)):
    """A recorded fingertip (index) with known values: IMU x = t, pressure = 1000 + t, audio ramps, frames = k."""
    meta = SessionMeta(source="real", object="mug", control_hz=20.0)
    h, w_ = image_hw
    streams = [StreamSetup("digit360/index/image", shape=(h, w_, 3)), StreamSetup("digit360/index/audio"),
               StreamSetup("digit360/index/imu"), StreamSetup("digit360/index/pressure")]
    with SessionWriter(path, meta, streams) as w:
        t_img = np.arange(int(duration * 30)) / 30.0 + 0.004  # a camera clock slightly offset from 0
        frames = np.broadcast_to((np.arange(len(t_img)) % 256).astype(np.uint8)[:, None, None, None],
                                 (len(t_img), h, w_, 3))
        w.append("digit360/index/image", frames, t_img)
        ta = np.arange(int(duration * 48000)) / 48000.0
        audio = np.stack([np.arange(len(ta)) % 20000, -(np.arange(len(ta)) % 20000)], axis=1).astype(np.int16)
        audio[ta > garbage_after] = 32767
        w.append("digit360/index/audio", audio, ta)
        ti = np.arange(int(duration * 400)) / 400.0
        imu = np.stack([ti, np.zeros_like(ti), np.ones_like(ti)], axis=1).astype(np.float32)
        imu[ti > garbage_after] = 99.0
        w.append("digit360/index/imu", imu, ti)
        tp = np.arange(int(duration * 200)) / 200.0
        p = (1000.0 + tp)[:, None].astype(np.float32)
        p[tp > garbage_after] = 2000.0
        w.append("digit360/index/pressure", p, tp)
    return path


def test_sim_windows_follow_the_contract(tmp_path):
    ds = TouchWindows([write_sim_session(tmp_path / "a.h5")])
    # windows end at frames 34 .. 59: frame 34 (1.133 s) is the first whose 1.12 s pressure window starts at >= 0
    assert len(ds) == 4 * 26 and ds.labels == ("force", "priv")
    s = ds[10]
    assert s["image"].shape == (6, 224, 224) and s["image"].dtype == torch.float32
    assert 0.0 <= s["image"].min() and s["image"].max() <= 1.0
    assert s["audio"].shape == (224, 256) and s["imu"].shape == (224, 3) and s["pressure"].shape == (224, 1)
    assert torch.isfinite(s["audio"]).all()
    assert 900 < s["pressure"].mean() < 1100  # hPa, about an atmosphere
    assert abs(s["imu"][:, 2].mean() - 1.0) < 0.1  # +1 g up at rest (9.81 m/s^2 / g)
    assert s["finger"] == 0 and s["time"] == pytest.approx((34 + 10) / 30)
    assert s["force"].shape == (3,) and s["priv"].shape == (9,)
    # the label is the last control step at or before the window's end
    assert s["force"][0] == np.floor(float(s["time"]) * 20 + 1e-9)


def test_windows_hold_no_future_samples(tmp_path):
    calm = TouchWindows([write_sim_session(tmp_path / "calm.h5")], labels=())
    wild = TouchWindows([write_sim_session(tmp_path / "wild.h5", wild_after=1.5)], labels=())
    frame = 45  # ends at exactly 1.5 s: the histories agree up to it and differ only after
    i = int(np.flatnonzero((calm.index[:, 1] == 2) & (calm.index[:, 2] == frame))[0])
    a, b = calm[i], wild[i]
    for k in ("image", "audio", "imu", "pressure"):
        assert torch.equal(a[k], b[k]), k
    j = int(np.flatnonzero((calm.index[:, 1] == 2) & (calm.index[:, 2] == frame + 3))[0])
    assert not torch.equal(calm[j]["audio"], wild[j]["audio"])  # ... and the difference does show up later


def test_windows_are_deterministic(tmp_path):
    path = write_sim_session(tmp_path / "a.h5")
    a, b = TouchWindows([path]), TouchWindows([path])
    for k in ("image", "audio", "imu", "pressure"):
        assert torch.equal(a[7][k], b[7][k]) and torch.equal(a[7][k], a[7][k])
    other = TouchWindows([write_sim_session(tmp_path / "b.h5", key=99)])
    assert not torch.equal(a[7]["audio"], other[7]["audio"])  # another session key: other noise


def test_recorded_session_resampled_causally(tmp_path):
    ds = TouchWindows([write_real_session(tmp_path / "real.h5", garbage_after=1.5)], fingers=["index"],
                      audio_features=False)
    t_img = np.arange(60) / 30.0 + 0.004
    # first window: its frame has 5 frames before it and 1.12 s of pressure behind it
    assert ds.end_times[0] == pytest.approx(t_img[np.flatnonzero(t_img >= 1.12)[0]])
    i = int(np.flatnonzero(ds.end_times < 1.5)[-1])
    s = ds[i]
    t_end = float(s["time"])
    assert t_end < 1.5
    assert s["image"].shape == (6, 224, 224)
    row = int(np.argmin(np.abs(t_img - t_end)))
    assert s["image"][0, 0, 0] * 255 == pytest.approx(row - 5) and s["image"][1, 0, 0] * 255 == pytest.approx(row)
    grid = t_end - np.arange(223, -1, -1) / 400.0
    newest = np.floor(t_end * 400) / 400.0  # the last IMU sample at or before t_end: held, never extrapolated
    assert np.allclose(s["imu"][:, 0].numpy(), np.minimum(grid, newest), atol=1e-5)  # x = t resampled linearly
    assert s["pressure"][-1, 0] == pytest.approx(1000.0 + np.floor(t_end * 200) / 200.0, abs=1e-3)
    wave = s["audio_wave"].numpy()
    last = int(np.floor(t_end * 48000 + 1e-6))
    assert wave.shape == (2, 27000) and wave[0, -1] == last % 20000 and wave.max() < 32767


def test_split_by_session_is_deterministic():
    paths = [f"s{i:02d}.h5" for i in range(10)]
    train, val = split_sessions(paths, 0.2, seed=3)
    assert len(val) == 2 and not set(train) & set(val) and len(train) + len(val) == 10
    assert (train, val) == split_sessions(list(reversed(paths)), 0.2, seed=3)
    assert split_sessions(paths, 0.2, seed=4) != (train, val)
    assert split_sessions(paths[:2], 0.01, seed=0)[1] != []  # both sides get a file
    with pytest.raises(ValueError, match="val_fraction"):
        split_sessions(paths, 1.0)


def test_bad_inputs_are_clear_errors(tmp_path):
    real = write_real_session(tmp_path / "real.h5")
    with pytest.raises(SessionError, match=r"real\.h5: fingertip 'thumb' has neither"):
        TouchWindows([real], fingers=["thumb"])
    with pytest.raises(ValueError, match="unknown finger"):
        TouchWindows([real], fingers=["pinky"])
    sim = write_sim_session(tmp_path / "sim.h5")
    with pytest.raises(SessionError, match=r"label\(s\) \['z'\] are missing"):
        TouchWindows([sim], labels=["z"])
    with SessionReader(sim) as r:
        assert r.meta.extra["touch_key"] == 1234
