"""Bottle shaking (envs.shake, envs.shake_contents): the sloshing model's figures by hand, the simulated liquid
rings at its predicted frequency and damping, episodes are deterministic per seed and the hand holds the bottle, in
the palm or (``grip='fingertips'``) on the four domes alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.constants import FINGERS
from envs.grasp_cache import load_default_cache
from envs.held_hand import wrist_spec
from envs.plug_grip import GRIP_RADIUS, fingertip_grip
from envs.shake import ShakeConfig, ShakeSim, draw_episode, parcels
from envs.shake_contents import CONTENT_NAMES, CONTENTS, FILL_LEVELS, Grain, slosh_model


@pytest.fixture(scope="module")
def grasps():
    return load_default_cache("cup", "", "digit360_v4")


def test_the_sloshing_model_matches_the_formulas_worked_by_hand():
    """Water in a cylinder of radius 30 mm filled 30 mm deep: tanh(1.8412) = 0.9511, w^2 = 9.81 x 1.8412 / 0.03 x
    0.9511 = 572.6 s^-2 (3.81 Hz); m1 / m = 2 x 0.9511 / (1.8412 x 2.3900) = 0.4323; Stephens' decrement 4.98 x 1e-3 x
    0.03^-0.75 x 9.81^-0.25 x (1 + 0.318 / sinh(1.8400)) = 0.04305, zeta = 0.006852."""
    s = slosh_model(CONTENTS["water"], 0.03, 0.03)
    assert s.omega**2 == pytest.approx(572.6, rel=2e-3)
    assert s.moving_mass / s.mass == pytest.approx(0.4323, rel=2e-3)
    assert s.mass == pytest.approx(998 * math.pi * 0.03**3, rel=1e-9)
    assert s.length == pytest.approx(9.81 / 572.6, rel=2e-3)
    assert s.damping_ratio == pytest.approx(0.006852, rel=5e-3)
    # oil is about 96 times as viscous: its decrement sqrt(92) = 9.6 times water's
    assert slosh_model(CONTENTS["oil"], 0.03, 0.03).damping_ratio / s.damping_ratio == pytest.approx(92**0.5, rel=1e-6)
    with pytest.raises(ValueError, match="radius and depth"):
        slosh_model(CONTENTS["water"], 0.03, 0.0)


def test_grains_have_their_stated_size_and_mass():
    pills, rice = CONTENTS["pills"], CONTENTS["rice"]
    assert isinstance(pills, Grain) and pills.mass == pytest.approx(0.0005)
    assert 2 * (pills.half_length + pills.radius) == pytest.approx(0.0217)
    assert 2 * (rice.half_length + rice.radius) == pytest.approx(0.0068) and rice.mass == pytest.approx(2.8e-5, rel=0.1)
    assert all(list(c.parcels) == sorted(c.parcels) for c in CONTENTS.values() if isinstance(c, Grain))


@pytest.mark.parametrize("name", ["pills", "rice", "lentils"])
@pytest.mark.parametrize("inner_r, inner_h", [(0.0265, 0.0565), (0.0425, 0.0905)])
def test_a_granular_fill_is_coarse_grained_parcels_carrying_the_pours_mass(name, inner_r, inner_h):
    """The fill's mass is the grain's density x 0.6 packing x the filled volume, worked by hand for rice at 45% of
    a 40 mm x 90 mm bottle (1450 x 0.6 x pi 0.04^2 0.0405 = 177 g); the parcels are the grain scaled alike in every
    dimension (never below a real grain), fit their start lattice without touching, and carry that mass."""
    content = CONTENTS[name]
    assert CONTENTS["rice"].fill_mass(0.04, 0.09, 2) == pytest.approx(1450 * 0.6 * math.pi * 0.04**2 * 0.0405)
    assert CONTENTS["rice"].fill_mass(0.04, 0.09, 2) == pytest.approx(0.177, rel=0.01)
    masses = []
    for level in range(3):
        parcel, slots = parcels(content, inner_r, inner_h, level, np.random.default_rng(level))
        k = parcel.radius / content.radius
        assert k >= 1.0 and parcel.half_length == pytest.approx(content.half_length * k)
        assert parcel.density == content.density and parcel.friction == content.friction
        masses.append(len(slots) * parcel.mass)
        assert masses[-1] == pytest.approx(content.fill_mass(inner_r, inner_h, level), rel=0.5 if k == 1.0 else 1e-6)
        # inside the bottle, and no two parcels' axes closer than a parcel's width (they start apart)
        assert np.all(np.abs(slots[:, 2]) <= inner_h / 2 - parcel.radius)
        assert np.all(np.hypot(slots[:, 1], np.abs(slots[:, 0]) + parcel.half_length) <= inner_r)
        for i in range(len(slots)):
            d = slots[i + 1:] - slots[i]
            same_row = (np.abs(d[:, 1]) < 1e-9) & (np.abs(d[:, 2]) < 1e-9)
            apart = np.where(same_row, np.abs(d[:, 0]) - 2 * (parcel.half_length + parcel.radius),
                             np.hypot(d[:, 1], d[:, 2]) - 2 * parcel.radius)
            assert np.all(apart > 0), (name, level, i)
    assert masses == sorted(masses) and masses[2] > 3 * masses[0]


def _ring(grasps, content: str, kick: float = 0.3) -> tuple[float, float, object]:
    """The liquid's pendulum swung by ``kick`` rad in a still hand: its measured frequency (Hz) and damping ratio,
    and the model's sloshing figures."""
    cfg = ShakeConfig(amplitude=(0.0, 0.0), tilt=(0.0, 0.0), duration_s=2.0, settle_s=0.0, ramp_s=0.0)
    ep = draw_episode(cfg, 3, grasps, content, 1)
    sim = ShakeSim(cfg, ep, grasps)
    sim.reset()
    adr = sim.model.jnt_qposadr[sim.model.joint("slosh_x").id]
    sim.data.qpos[adr] = kick
    angles = []
    import mujoco

    for _ in range(1000):
        mujoco.mj_step(sim.model, sim.data)
        angles.append(sim.data.qpos[adr])
    a = np.asarray(angles) - np.mean(angles[-200:])
    up = np.flatnonzero((a[:-1] < 0) & (a[1:] >= 0))  # upward zero crossings
    freq = (len(up) - 1) / ((up[-1] - up[0]) * sim.model.opt.timestep)
    peaks = [a[i:j].max() for i, j in zip(up[:-1], up[1:], strict=True)]
    zeta = math.log(peaks[0] / peaks[-1]) / (len(peaks) - 1) / (2 * math.pi)
    inner_r, inner_h = _inside(grasps, ep.bucket)
    return freq, zeta, slosh_model(CONTENTS[content], inner_r, CONTENTS[content].fills[1] * inner_h)


def _inside(grasps, bucket: int) -> tuple[float, float]:
    """The inner radius and height (m) of the bottle of a grasp bucket: the cup's 40 x 85 mm at its scale, less the
    1.5 mm wall (the bottom and cap at both ends)."""
    scale = float(grasps.scales[bucket])
    return 0.040 * scale - 0.0015, 0.085 * scale - 0.003


def test_the_simulated_liquid_rings_at_its_sloshing_frequency_and_oil_damps_it_faster(grasps):
    f_water, z_water, model = _ring(grasps, "water")
    assert f_water == pytest.approx(model.omega / (2 * math.pi), rel=0.08), (f_water, model.omega / (2 * math.pi))
    f_oil, z_oil, model_oil = _ring(grasps, "oil")
    assert f_oil == pytest.approx(model_oil.omega / (2 * math.pi), rel=0.08)
    assert z_oil == pytest.approx(model_oil.damping_ratio, rel=0.35), (z_oil, model_oil.damping_ratio)
    assert z_oil > 4 * z_water


def test_an_episode_is_deterministic_per_seed_and_the_hand_holds_the_bottle(grasps):
    cfg = ShakeConfig(duration_s=1.2)
    ep = draw_episode(cfg, 21, grasps, "pills", 1)
    assert ep == draw_episode(cfg, 21, grasps, "pills", 1) and ep != draw_episode(cfg, 22, grasps, "pills", 1)
    a, b = ShakeSim(cfg, ep, grasps).run(), ShakeSim(cfg, ep, grasps).run()
    assert np.array_equal(a.contact, b.contact) and np.array_equal(a.times, b.times)
    assert a.contact.shape == (4, 600, a.contact.shape[2]) and np.all(np.isfinite(a.contact))
    inner_r, inner_h = _inside(grasps, ep.bucket)
    assert a.held and a.content_mass == pytest.approx(CONTENTS["pills"].fill_mass(inner_r, inner_h, 1), rel=1e-6)
    assert a.contact[:, :, 0].max() > 0.05  # some fingertip presses on the bottle
    # the wrist moved: once the shake is on (after 0.6 s) the fingertips' accelerometers leave gravity's 9.81 m/s^2
    # more than twice as far as while the bottle settled (2.9 m/s^2 peak wrist acceleration in this episode)
    deviation = np.abs(np.linalg.norm(a.contact[:, :, 3:6], axis=-1) - 9.81)
    assert deviation[:, 300:].mean() > 2 * deviation[:, :100].mean()


def test_draws_cover_every_content_and_level_and_cap_the_acceleration(grasps):
    cfg = ShakeConfig()
    eps = [draw_episode(cfg, s, grasps) for s in range(200)]
    assert {e.content for e in eps} == set(CONTENT_NAMES) and {e.fill for e in eps} == set(range(len(FILL_LEVELS)))
    assert all(e.amplitude * (2 * math.pi * e.frequency) ** 2 <= cfg.max_accel + 1e-9 for e in eps)
    with pytest.raises(ValueError, match="unknown content"):
        draw_episode(cfg, 0, grasps, "sand")
    with pytest.raises(ValueError, match="fill must be"):
        draw_episode(cfg, 0, grasps, "rice", 3)
    with pytest.raises(ValueError, match="Digit 360"):
        ShakeConfig(hand="xela_v4")


@pytest.mark.parametrize("amplitude, frequency", [(0.015, 2.0), (0.005, 4.0), (0.02, 1.5)])
def test_strokes_travel_the_amplitude_at_constant_speed_and_reverse_at_the_largest_acceleration(amplitude,
                                                                                               frequency):
    """envs.shake.stroke, against finite differences: the travel is +-A, the acceleration never exceeds max_accel
    and reaches it at each reversal, the speed between reversals is constant, and it crosses the middle moving up
    where the sinusoid does. Worked by hand at A = 15 mm, 2 Hz, 5 m/s^2: 2 V^2 / a - V T + 4 A = 0 gives
    V = (0.5 - sqrt(0.25 - 0.096)) x 5 / 4 = 0.13446 m/s (the sinusoid's peak: 2 pi f A = 0.1885 m/s)."""
    from envs.shake import stroke

    a = ShakeConfig().max_accel
    amplitude = min(amplitude, a / (2 * math.pi * frequency) ** 2)  # draw_episode's cap
    dt = 1e-5
    t = np.arange(0.0, 2.0 / frequency, dt)
    x = np.array([stroke(frequency * ti, amplitude, frequency, a) for ti in t]) * amplitude
    v, acc = np.gradient(x, dt), np.gradient(np.gradient(x, dt), dt)
    assert x.max() == pytest.approx(amplitude, rel=1e-6) and x.min() == pytest.approx(-amplitude, rel=1e-6)
    assert np.abs(acc[2:-2]).max() == pytest.approx(a, rel=1e-3)
    cruising = np.abs(acc) < 1e-6
    assert cruising.mean() > 0.5 and np.ptp(np.abs(v[cruising])) < 1e-6
    assert abs(x[0]) < 1e-12 and v[0] > 0
    if (amplitude, frequency) == (0.015, 2.0):
        assert np.abs(v).max() == pytest.approx(0.13446, rel=1e-3)
    with pytest.raises(ValueError, match="need more than"):
        stroke(0.0, 0.05, 2.0, a)  # 50 mm strokes at 2 Hz would need 6.4 m/s^2


def test_a_strokes_episode_moves_the_hand_by_strokes(grasps):
    """The same episode's draws shaken by strokes instead of a sinusoid: deterministic, the bottle held, the wrist
    target on the stroke profile, and the palm itself (welded to it) accelerating along the shake's direction up to
    max_accel at the reversals (measured: 5.2 m/s^2), where the sinusoid's palm peaks at (2 pi f)^2 A (2.9)."""
    from envs.shake import TIMESTEP, stroke

    ep = draw_episode(ShakeConfig(duration_s=1.5), 21, grasps, "pills", 2)
    peaks, runs = {}, {}
    for motion in ("sine", "strokes"):
        cfg = ShakeConfig(duration_s=1.5, motion=motion)
        sim = ShakeSim(cfg, ep, grasps)
        if motion == "strokes":
            expected = stroke(ep.frequency + ep.phase / (2 * math.pi), ep.amplitude, ep.frequency, cfg.max_accel)
            assert np.allclose(sim._wrist(1.0)[0], ep.amplitude * expected * np.asarray(ep.direction), atol=1e-12)
        palm, path = sim.model.body("palm").id, []
        runs[motion] = sim.run(on_step=lambda d, palm=palm, path=path: path.append(d.xpos[palm].copy()))
        acc = np.gradient(np.gradient(np.asarray(path), TIMESTEP, axis=0), TIMESTEP, axis=0)[350:]
        peaks[motion] = float(np.percentile(np.abs(acc @ np.asarray(ep.direction)), 99))
    assert peaks["strokes"] == pytest.approx(ShakeConfig().max_accel, rel=0.1), peaks
    assert peaks["sine"] == pytest.approx((2 * math.pi * ep.frequency) ** 2 * ep.amplitude, rel=0.1), peaks
    again = ShakeSim(ShakeConfig(duration_s=1.5, motion="strokes"), ep, grasps).run()
    assert np.array_equal(again.contact, runs["strokes"].contact) and runs["strokes"].held
    with pytest.raises(ValueError, match="motion must be"):
        ShakeConfig(motion="swirl")


CONTENTS_BODIES = ("grain", "slosh")
"""The bodies inside the bottle: their contacts with its wall are not the hand's."""


def test_the_fingertip_grip_stands_the_bottle_on_the_four_domes_alone(grasps, touching):
    """With ``grip='fingertips'`` (envs.plug_grip) only the fingertips touch the bottle, all four domes press on it,
    its lowest 30 mm stand where the plug's disc would, it is the cup grasp's size at most GRIP_RADIUS across, and it
    stays in the hand through a shake; the domes press it several times as hard as in the palm grip of the same
    episode (measured 0.7 s in, seeds 10-14: 9.5-20 N on the hand, 70-100% of it on the domes, against 1.6-5.9 N and
    35-70%)."""
    cfg = ShakeConfig(duration_s=1.2, grip="fingertips")
    ep = draw_episode(cfg, 10, grasps, "water", 1)
    sim = ShakeSim(cfg, ep, grasps)
    rec = sim.run()
    on_hand = touching(sim, "bottle", CONTENTS_BODIES)
    assert all(n.endswith(("_tip", "_digit360")) for n in on_hand), on_hand
    assert {f for f in FINGERS if on_hand.get(f"{f}_tip", 0.0) > 0.05} == set(FINGERS), on_hand
    assert rec.held and np.all(np.isfinite(rec.contact))
    radius = min(0.040 * float(grasps.scales[ep.bucket]), GRIP_RADIUS)
    assert sim.model.geom("bottle_bottom").size[0] == pytest.approx(radius)
    domes = sum(on_hand[f"{f}_tip"] for f in FINGERS)
    palm_cfg = ShakeConfig(duration_s=1.2)
    palm = ShakeSim(palm_cfg, draw_episode(palm_cfg, 10, grasps, "water", 1), grasps)
    palm.run()
    palm_on_hand = touching(palm, "bottle", CONTENTS_BODIES)
    palm_domes = sum(palm_on_hand.get(f"{f}_tip", 0.0) for f in FINGERS)
    assert domes > 2 * palm_domes, (on_hand, palm_on_hand)
    with pytest.raises(ValueError, match="grip must be one of fingertips, palm"):
        ShakeConfig(grip="pinch")
    with pytest.raises(ValueError, match="at least 0.03 m tall"):
        fingertip_grip(wrist_spec(cfg.hand, 0.002)[0], sim._run.grip, 0.02)
