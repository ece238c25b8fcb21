"""The generation-2 simulated Digit 360 (envs.sensors.digit360_markers, the generation-2 parts of
digit360_signals): the streams carry what the contact holds, stay causal and deterministic, and the shipped
generation 1 is untouched."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from envs.scene import touch_model
from envs.sensors import digit360_image as I
from envs.sensors import digit360_model as M
from envs.sensors import digit360_render as R
from envs.sensors import digit360_signals as S
from envs.sensors.digit360 import FIELD, FINGERS, NUM_FIELDS, Digit360Readout, add_digit360_sensors
from envs.sensors.digit360_markers import surface_shift

GEN2 = M.CONTACT_MODEL


def contact_row(fn: float, ft: float, slip: float, theta_deg: float = 40.0, radius: float = 0.012) -> np.ndarray:
    """One contact-field row: a dome pressed with ``fn`` N at ``theta_deg`` from its apex, dragged with ``ft`` N
    along the sensor's y axis (tangent there), the contact point slipping at ``slip`` m/s."""
    row = np.zeros(NUM_FIELDS, np.float32)
    t = math.radians(theta_deg)
    point = radius * np.array([math.sin(t), 0.0, math.cos(t)])
    force = -fn * point / radius + ft * np.array([0.0, 1.0, 0.0])  # on the dome: pressed inward, dragged along y
    row[FIELD["force_x"]], row[FIELD["force_y"]], row[FIELD["force_n"]] = force[0], force[1], -force[2]
    row[FIELD["c0_found"]], row[FIELD["c0_fn"]], row[FIELD["c0_slip"]] = 1.0, fn, slip
    for axis, value in zip("xyz", point, strict=True):
        row[FIELD[f"c0_{axis}"]] = value
    row[FIELD["acc_z"]] = 9.81
    return row


def test_hands_pick_their_generation():
    assert touch_model("digit360") == M.DEFAULT_MODEL  # the shipped encoder's streams, bit for bit
    assert touch_model("digit360_v4") == GEN2 and GEN2.generation == 2 and GEN2.dome_radius == 0.012
    with pytest.raises(ValueError, match="generation"):
        M.Digit360Model(generation=3)
    with pytest.raises(ValueError, match="imu_mode"):
        M.Digit360Model(imu_mode=(250.0, 0.01))  # above the 400 Hz samples' Nyquist limit


def test_the_resting_image_keeps_the_released_mean_and_each_sensor_its_own_lighting():
    rest = np.zeros(NUM_FIELDS, np.float32)
    frames = [I.render_frame(rest, 3, key=1, sensor=f, model=GEN2) for f in range(4)]
    for img in frames:  # markers included, the mean colour is the released Sparsh-X image mean
        assert np.allclose(img.reshape(-1, 3).mean(0) / 255, GEN2.background_mean, atol=0.01)
    assert np.abs(frames[0].astype(int) - frames[1].astype(int)).mean() > 2  # lights and lens differ per sensor
    dark = frames[0].min(-1)[100:124, 100:124]  # the marker grid near the centre: dark dots between bright gel
    assert dark.max() - dark.min() > 15


def test_sliding_and_sticking_contacts_of_the_same_force_look_different():
    stick = I.render_frame(contact_row(2.0, 0.8, 0.0), 5, key=3, model=GEN2).astype(int)
    slide = I.render_frame(contact_row(2.0, 0.8, 0.02), 5, key=3, model=GEN2).astype(int)
    still = I.render_frame(contact_row(2.0, 0.0, 0.0), 5, key=3, model=GEN2).astype(int)
    assert (np.abs(slide - stick).max(-1) > 10).sum() > 100  # the markers in the patch moved differently
    assert (np.abs(stick - still).max(-1) > 10).sum() > 100  # and shear moves them at all
    # generation 1 cannot tell them apart: its image reads no slip
    g1 = [I.render_frame(contact_row(2.0, 0.8, s, radius=0.014), 5, key=3) for s in (0.0, 0.02)]
    assert np.array_equal(g1[0], g1[1])


def test_sticking_shifts_the_patch_rigidly_sliding_fans_it_out():
    """Mindlin (sticking): the whole contact moves by (2 - nu) Q / (8 G a); full slip under Hertz-shaped traction:
    1.5 times that at the centre, less at the rim (Johnson 1985, chapter 7)."""
    fn, q = 2.0, 0.8
    a = (3 * fn * GEN2.dome_radius / (4 * GEN2.elastomer_modulus)) ** (1 / 3)
    g = GEN2.elastomer_modulus * (1 - GEN2.poisson**2) / (2 * (1 + GEN2.poisson))
    delta = (2 - GEN2.poisson) * q / (8 * g * a)  # m
    px_per_m = 112 / (math.radians(GEN2.fov_half_angle_deg) * GEN2.dome_radius)
    centre = (int(round(111.5)), int(round(111.5 + 40 / GEN2.fov_half_angle_deg * 112)))  # (row, col) at 40 deg
    for slip, want in ((0.0, 1.0), (0.02, 1.5)):
        shift = surface_shift(contact_row(fn, q, slip), GEN2, 224)
        moved = shift[centre][1]  # along the image rows: the drag is along the sensor's y axis
        assert moved == pytest.approx(want * delta * px_per_m, rel=0.1), (slip, moved)
        assert abs(shift[centre][0]) < 0.05 * abs(moved)
    rim = (centre[0] + int(0.8 * a * px_per_m), centre[1])  # 0.8 a along the drag
    stick, slide = (surface_shift(contact_row(fn, q, s), GEN2, 224)[rim][1] for s in (0.0, 0.02))
    assert stick == pytest.approx(delta * px_per_m, rel=0.1) and slide < 1.2 * stick  # the rim lags when sliding


def _sliding_track(seconds: float = 2.0, ft: float = 0.5, knock_at: float = 1.2) -> M.ContactTrack:
    times = np.arange(int(seconds / 0.01)) * 0.01
    rows = np.stack([contact_row(1.0 + (1.0 if t >= knock_at else 0.0), ft, 0.03 if t >= 0.5 else 0.0)
                     for t in times])
    return M.ContactTrack(times, rows, 0.01)


def test_generation2_streams_are_causal_and_deterministic():
    track = _sliding_track()
    cut = M.ContactTrack(track.times[track.times <= 1.5], track.rows[track.times <= 1.5], 0.01)
    a, b = R.render_window(track, 45, key=3, model=GEN2), R.render_window(cut, 45, key=3, model=GEN2)
    again = R.render_window(track, 45, key=3, model=GEN2)
    for k in a:
        assert np.array_equal(a[k], b[k]), f"{k} used rows after the window's end"
        assert np.array_equal(a[k], again[k])
    # two windows cut from one track agree on their overlap (the gel lag and the vibration look back a fixed time)
    late = R.render_window(track, 55, key=3, model=GEN2)  # 10 frames later: 1/3 s
    dp = int(R.WindowIndex(55).pressure[0] - R.WindowIndex(45).pressure[0])
    di = int(R.WindowIndex(55).imu[0] - R.WindowIndex(45).imu[0])
    assert np.array_equal(a["pressure"][dp:], late["pressure"][:-dp])
    assert np.array_equal(a["imu"][di:], late["imu"][:-di])


def test_pressure_follows_the_force_through_the_gel_lag():
    times = np.arange(200) * 0.01
    rows = np.stack([contact_row(2.0 if t >= 1.0 else 0.0, 0.0, 0.0) for t in times])
    rows[times < 1.0, FIELD["c0_found"]] = 0
    track = M.ContactTrack(times, rows, 0.01)
    samples = np.arange(0, 400)
    p = S.render_pressure(track, samples, key=3, model=GEN2) - S.pressure_terms(samples, 3, GEN2)[0]
    p1 = S.render_pressure(track, samples, key=3) - S.pressure_terms(samples, 3)[0]
    rise = 2.0 * GEN2.pressure_per_newton
    tau = GEN2.gel_time_constant
    at = lambda t: p[int(round((1.0 + 0.01 + t) * 200))]  # the step is seen one physics step late  # noqa: E731
    assert at(-0.02) == pytest.approx(0.0, abs=0.15)
    assert at(tau) == pytest.approx(rise * (1 - math.exp(-1)), abs=0.25 * rise)  # 63% after one time constant
    assert at(5 * tau) == pytest.approx(rise, abs=0.15)
    assert p1[int(1.02 * 200)] == pytest.approx(rise, abs=0.15)  # generation 1 has no lag


def test_friction_power_drives_the_slip_sound_and_the_accelerometer():
    """While sliding, the tangential force is mu x F_n: the same press and slip speed with twice the friction
    (twice the tangential force) doubles the frictional power, and the slip noise of audio and IMU follows it."""

    def loudness(ft: float, model: M.Digit360Model) -> tuple[float, float]:
        track = _sliding_track(ft=ft, knock_at=99.0)
        audio = S.render_audio(track, int(1.0 * 48000), 24000, key=3, model=model)  # 1.0 .. 1.5 s: sliding
        imu = S.render_imu(track, np.arange(400, 600), key=3, model=model)
        hp = imu - imu.mean(0)
        return float(audio.std()), float(hp.std())

    (a1, i1), (a2, i2) = loudness(0.3, GEN2), loudness(0.6, GEN2)
    assert a2 > 1.6 * a1 and i2 > 1.6 * i1
    g1 = loudness(0.3, M.DEFAULT_MODEL), loudness(0.6, M.DEFAULT_MODEL)
    assert g1[1][0] == pytest.approx(g1[0][0], rel=0.05)  # generation 1 hears F_n x v: blind to friction


def test_an_impact_shakes_the_accelerometer_above_the_physics_rate():
    track = _sliding_track(ft=0.0, knock_at=1.2)
    samples = np.arange(int(1.0 * 400), int(1.6 * 400))
    freq = np.fft.rfftfreq(len(samples), 1 / M.IMU_HZ)

    def band_power(model: M.Digit360Model) -> tuple[float, np.ndarray]:
        imu = S.render_imu(track, samples, key=3, model=model)
        power = (np.abs(np.fft.rfft(imu - imu.mean(0), axis=0)) ** 2).sum(1)
        return float(power[(freq > 60) & (freq < 190)].sum()), imu

    (high, imu), (high1, _) = band_power(GEN2), band_power(M.DEFAULT_MODEL)
    assert high > 100 * high1  # generation 1: the physics rate's samples interpolated, plus white noise
    assert np.abs(imu - imu.mean(0)).max() > 0.5  # a 1 N knock on 50 g: about 2 g of ringing


LOAD_XML = """
<mujoco>
  <option timestep="0.01" cone="elliptic" impratio="10"/>
  <worldbody>
    {domes}
    <body name="load" pos="0 0 {top}">
      <joint type="slide" axis="0 0 1"/>
      <geom type="box" size="0.015 0.015 0.003" mass="{mass}"/>
    </body>
  </worldbody>
</mujoco>
"""


def _loaded_dome_pressure(mass: float) -> float:
    """Pressure rise (hPa) of a dome carrying a ``mass`` kg plate that rests on it (the physics' weight)."""
    domes = "".join(f'<body pos="{0.05 * i} 0 0.1"><geom name="{f}_tip" type="sphere" size="0.012"/>'
                    f'<site name="{f}_tip"/></body>' for i, f in enumerate(FINGERS))
    spec = mujoco.MjSpec.from_string(LOAD_XML.format(domes=domes, top=0.1 + 0.012 + 0.003, mass=mass))
    add_digit360_sensors(spec, history=1)
    model = spec.compile()
    data = mujoco.MjData(model)
    readout = Digit360Readout(model)
    rows, times = [], []
    for k in range(100):
        mujoco.mj_step(model, data)
        rows.append(readout.read_current(data.sensordata[None])[0, 0, 0])
        times.append(k * 0.01)
    track = M.ContactTrack(np.array(times), np.stack(rows), 0.01)
    samples = np.arange(150, 190)  # 0.75 .. 0.95 s: settled
    p = S.render_pressure(track, samples, key=3, model=GEN2) - S.pressure_terms(samples, 3, GEN2)[0]
    return float(p.mean())


def test_a_heavier_load_raises_the_pressure_reading():
    light, heavy = _loaded_dome_pressure(0.05), _loaded_dome_pressure(0.25)
    want = GEN2.pressure_per_newton * 9.81
    assert light == pytest.approx(0.05 * want, abs=0.3) and heavy == pytest.approx(0.25 * want, abs=0.3)
