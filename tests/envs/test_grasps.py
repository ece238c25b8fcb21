"""Grasp cache: file round trip, sampling by hand, clear errors for bad files, a tiny generation whose grasps
satisfy Hora's acceptance rule when checked with MuJoCo's own distance query (not the generator's own geometry), and
the hold check, compared with the env itself holding still."""

from __future__ import annotations

import itertools
from dataclasses import replace

import mujoco
import numpy as np
import pytest

from envs import EnvConfig, RotateCupVec
from envs import constants as C
from envs.config import Perturbation, default_randomization
from envs.constants import DEFAULT_HAND
from envs.grasp_cache import GRASP_DIM, GraspCache, default_cache_path, load_default_cache
from envs.grasps import HOLD_DROP, HoldRule, generate_grasps, hold_check
from envs.objects import get_object
from envs.scene import CANONICAL_POSE, OBJECT_BODY, OBJECT_START, build_model, hand_variant

SCALES = (0.74, 0.82)
_BUCKETS = default_randomization(DEFAULT_HAND).scales
NOMINAL_SCALE = _BUCKETS[len(_BUCKETS) // 2]
"""The default hand's nominal object scale: the middle bucket, where a nominal env (randomization off) starts."""


@pytest.fixture(scope="module")
def generated():
    return generate_grasps("cylinder", SCALES, per_scale=3, batch_size=8, max_rounds=20, seed=0, nthread=1)


def small_cache(obj: str = "cylinder") -> GraspCache:
    """2 buckets x 4 rows of the canonical pose; row g of bucket b has joint 0 = (10 b + g) / 100 rad, so a sampled
    row tells where it came from."""
    grasps = np.zeros((2, 4, GRASP_DIM))
    grasps[:, :, :16] = CANONICAL_POSE
    grasps[:, :, 0] = (10 * np.arange(2)[:, None] + np.arange(4)[None]) / 100
    grasps[:, :, 16:19] = OBJECT_START
    grasps[:, :, 19] = 1.0  # identity quaternion
    return GraspCache(obj, np.array([0.7, 0.8]), grasps, seed=4)


def test_sample_picks_the_nearest_bucket_and_the_row_by_u():
    q, pose = small_cache().sample(np.zeros(4, int), np.array([0.71, 0.79, 0.76, 0.74]), np.array([0, 0.99, 0.5, 0.3]))
    # 0.76 is nearer 0.8 than 0.7; 0.74 nearer 0.7; row = floor(u x 4)
    np.testing.assert_array_equal(np.round(q[:, 0] * 100), [0, 13, 12, 1])
    assert q.shape == (4, 16) and pose.shape == (4, 7)
    np.testing.assert_array_equal(pose[:, 3], 1.0)


def test_save_load_round_trip(tmp_path, generated):
    path = tmp_path / "sub" / "cache"  # no .npz suffix: the file is written at exactly this path
    generated.save(path)
    assert path.is_file()
    loaded = GraspCache.load(path)
    assert loaded.object == "cylinder" and loaded.seed == 0
    np.testing.assert_array_equal(loaded.scales, SCALES)
    # grasps are stored as float32 (half the file); loading gives those values back exactly
    np.testing.assert_array_equal(loaded.grasps, generated.grasps.astype(np.float32))
    np.testing.assert_allclose(loaded.grasps, generated.grasps, atol=1e-6)
    loaded.save(tmp_path / "again.npz")
    again = GraspCache.load(tmp_path / "again.npz")
    np.testing.assert_array_equal(again.grasps, loaded.grasps)
    np.testing.assert_array_equal(again.scales, loaded.scales)


def test_generated_grasps_follow_horas_rule(generated):
    """All four fingertips within 10 cm of the object centre, at least two touching it, object still in the hand
    (near the centre the grasps of the hand they were generated on start from)."""
    obj = get_object("cylinder")
    assert generated.grasps.shape == (len(SCALES), 3, GRASP_DIM) and generated.hand == DEFAULT_HAND
    start = hand_variant(generated.hand).object_start
    tip_geoms = [f"{finger}_tip" for finger in C.FINGERS]
    for scale, rows in zip(SCALES, generated.grasps, strict=True):
        model = build_model(obj, scale, hand=generated.hand)
        data = mujoco.MjData(model)
        o = model.joint("object_free").qposadr[0]
        obj_geoms = np.flatnonzero(model.geom_bodyid == model.body(OBJECT_BODY).id)
        for row in rows:
            q, pose = row[:16], row[16:]
            assert np.all((q >= C.JOINT_LOWER - 0.02) & (q <= C.JOINT_UPPER + 0.02))  # PD overshoot is tiny
            assert abs(np.linalg.norm(pose[3:]) - 1.0) < 1e-6
            data.qpos[:16], data.qpos[o : o + 7] = q, pose
            mujoco.mj_forward(model, data)
            centre = data.xpos[model.body(OBJECT_BODY).id]
            tips = np.array([data.site(s).xpos for s in C.FINGERTIP_SITES])
            assert np.linalg.norm(tips - centre, axis=1).max() < 0.10
            gap = [min(mujoco.mj_geomDistance(model, data, model.geom(t).id, g, 0.05, None) for g in obj_geoms)
                   for t in tip_geoms]
            assert sum(d < 0.004 for d in gap) >= 2, gap  # touching: within the generator's 4 mm tolerance
            # did not fall: still above the fingers' base, near where grasps start (the hand's object start; 99% of
            # the shipped caches' objects of either Digit 360 hand settle within 4 cm of it sideways)
            assert start[2] - 0.04 < pose[2] < start[2] + 0.02
            assert np.linalg.norm(pose[:2] - start[:2]) < 0.04


def test_generation_is_seeded(generated):
    again = generate_grasps("cylinder", SCALES, per_scale=3, batch_size=8, max_rounds=20, seed=0, nthread=1)
    np.testing.assert_array_equal(again.grasps, generated.grasps)


def test_env_resets_into_a_generated_cache(tmp_path, generated):
    generated.save(tmp_path / "g.npz")
    cfg = EnvConfig(object="cylinder", grasp_cache=str(tmp_path / "g.npz"))
    core = RotateCupVec(cfg, num_envs=4, seed=0, nthread=1)
    core.reset(seed=0)
    rows = GraspCache.load(tmp_path / "g.npz").grasps.reshape(-1, GRASP_DIM)
    for q in core.batch.bind("qpos")[:, :16]:
        assert np.any(np.all(rows[:, :16] == q, axis=1))  # every env starts from one of the cached rows


def test_missing_file(tmp_path):
    with pytest.raises(ValueError, match=r"grasp cache .*nope\.npz does not exist.*rotate grasps"):
        GraspCache.load(tmp_path / "nope.npz")
    with pytest.raises(ValueError, match="does not exist"):
        RotateCupVec(EnvConfig(object="cylinder", grasp_cache=str(tmp_path / "nope.npz")))


def corruptions(good: bytes) -> dict[str, bytes]:
    zeroed = bytearray(good)
    zeroed[len(good) // 3 : len(good) // 3 + 64] = bytes(64)  # damages a compressed member (CRC error)
    early = bytearray(good)
    early[200:264] = bytes(64)  # damages the deflate stream itself
    return {"garbage": b"not a grasp cache " * 20, "empty": b"", "truncated": good[: len(good) // 2],
            "zeroed": bytes(zeroed), "zeroed_early": bytes(early)}


@pytest.mark.parametrize("kind", ["garbage", "empty", "truncated", "zeroed", "zeroed_early"])
def test_corrupted_file(tmp_path, kind):
    small_cache().save(tmp_path / "good.npz")
    bad = tmp_path / f"{kind}.npz"
    bad.write_bytes(corruptions((tmp_path / "good.npz").read_bytes())[kind])
    with pytest.raises(ValueError, match=rf"grasp cache .*{kind}\.npz is (not a readable \.npz file|corrupted)"):
        GraspCache.load(bad)


def test_wrong_contents(tmp_path):
    np.savez(tmp_path / "keys.npz", object="cylinder", grasps=np.zeros((1, 2, GRASP_DIM)))
    with pytest.raises(ValueError, match=r"missing \['scales'\]"):
        GraspCache.load(tmp_path / "keys.npz")
    np.savez(tmp_path / "shape.npz", object="cylinder", scales=np.ones(2), grasps=np.zeros((2, 3, 20)))
    with pytest.raises(ValueError, match=r"shape \(S=2, G, 23\), got \(2, 3, 20\)"):
        GraspCache.load(tmp_path / "shape.npz")
    np.savez(tmp_path / "nan.npz", object="cylinder", scales=np.ones(1), grasps=np.full((1, 2, GRASP_DIM), np.nan))
    with pytest.raises(ValueError, match="non-finite"):
        GraspCache.load(tmp_path / "nan.npz")
    np.save(tmp_path / "array.npy", np.zeros(3))
    (tmp_path / "array.npy").rename(tmp_path / "array.npz")
    with pytest.raises(ValueError, match=r"single \.npy array"):
        GraspCache.load(tmp_path / "array.npz")


def test_cache_for_another_object_is_refused(tmp_path):
    small_cache("cylinder").save(tmp_path / "cyl.npz")
    with pytest.raises(ValueError, match="generated for 'cylinder', not for 'cup'"):
        load_default_cache("cup", str(tmp_path / "cyl.npz"))
    with pytest.raises(ValueError, match="generated for 'cylinder', not for 'cup'"):
        RotateCupVec(EnvConfig(object="cup", grasp_cache=str(tmp_path / "cyl.npz")))


def test_object_without_a_shipped_cache():
    on = "" if DEFAULT_HAND == "digit360" else f" on the {DEFAULT_HAND} hand"  # the default hand's caches
    with pytest.raises(ValueError, match=rf"no grasp cache ships for object 'cylinder_3'{on} \(shipped: .*cylinder"):
        RotateCupVec(EnvConfig(object="cylinder_3"))
    with pytest.raises(ValueError, match=r"no grasp cache ships for object 'cylinder_3' \(shipped: .*cylinder.*"
                                         r"`rotate grasps --objects cylinder_3 --out DIR`"):
        RotateCupVec(EnvConfig(object="cylinder_3", hand="digit360"))


def test_generate_rejects_bad_budgets():
    with pytest.raises(ValueError, match="per_scale must be >= 1"):
        generate_grasps("cylinder", (0.8,), per_scale=0)
    with pytest.raises(ValueError, match="unknown object 'mug'"):
        generate_grasps("mug", (0.8,), per_scale=1)


def _saved_with(tmp_path, name: str, edit) -> str:
    """A copy of the small cache with one edit, saved as ``name``; returns the path."""
    cache = small_cache()
    grasps, scales = cache.grasps.copy(), cache.scales.copy()
    edit(grasps, scales)
    path = tmp_path / name
    np.savez(path, object="cylinder", scales=scales, grasps=grasps, seed=0)
    return str(path)


BAD_ROWS = {
    # name: (edit of (grasps, scales), the message must match)
    "joint_high": (lambda g, s: g.__setitem__((1, 2, 5), 2.5),
                   r"bad\.npz: bucket 1 \(scale 0\.8\), row 2: joint 5 \(middle_1\) = 2\.5000 rad is outside its "
                   r"limits \[-0\.196, 1\.61\]"),
    "joint_low": (lambda g, s: g.__setitem__((0, 3, 12), 0.0),
                  r"bucket 0 \(scale 0\.7\), row 3: joint 12 \(thumb_0\) = 0\.0000 rad is outside its limits"),
    "quaternion": (lambda g, s: g.__setitem__((0, 1, 19), 0.5),
                   r"bucket 0 \(scale 0\.7\), row 1: the object quaternion has norm 0\.5\d*, not 1"),
    "far_object": (lambda g, s: g.__setitem__((1, 0, 18), 0.5),
                   r"bucket 1 \(scale 0\.8\), row 0: the object centre .* m from the hand's grasp point"),
    "nan_row": (lambda g, s: g.__setitem__((1, 3, 7), np.nan), r"bucket 1 \(scale 0\.8\), row 3: non-finite values"),
    "nan_scale": (lambda g, s: s.__setitem__(0, np.nan), r"bad\.npz: scales must be finite numbers in \[0\.1, 3\.0\]"),
    "zero_scale": (lambda g, s: s.__setitem__(1, 0.0), r"scales must be finite numbers in \[0\.1, 3\.0\]"),
}


@pytest.mark.parametrize("kind", list(BAD_ROWS))
def test_bad_rows_name_the_file_and_the_row(tmp_path, kind):
    edit, message = BAD_ROWS[kind]
    path = _saved_with(tmp_path, "bad.npz", edit)
    with pytest.raises(ValueError, match=message):
        GraspCache.load(path)
    with pytest.raises(ValueError, match=message):  # also through the env
        RotateCupVec(EnvConfig(object="cylinder", grasp_cache=path))


def test_unknown_object_in_the_file(tmp_path):
    np.savez(tmp_path / "mug.npz", object="mug", scales=small_cache().scales, grasps=small_cache().grasps)
    with pytest.raises(ValueError, match=r"mug\.npz: unknown object 'mug'; known objects: cup"):
        GraspCache.load(tmp_path / "mug.npz")


def test_shipped_caches_are_valid():
    """Every object's cache ships for both Digit 360 hands (the default one among them), under its file name
    (grasps_<object>.npz for 'digit360', grasps_<object>_<hand>.npz for another hand), and was generated on that
    hand; loading checks every row."""
    assert DEFAULT_HAND in ("digit360", "digit360_v4")
    for hand, name in itertools.product(("digit360", "digit360_v4"), ("cup", "cup_small", "cup_large", "cylinder")):
        file = f"grasps_{name}.npz" if hand == "digit360" else f"grasps_{name}_{hand}.npz"
        assert default_cache_path(name, hand).name == file
        cache = GraspCache.load(default_cache_path(name, hand))
        assert cache.source.endswith(file) and cache.object == name and cache.hand == hand
    assert default_cache_path("cup") == default_cache_path("cup", DEFAULT_HAND)


@pytest.fixture(scope="module")
def cup_grasps():
    """16 cup grasps of the default hand at its nominal scale that pass Hora's rule but not all of the hold check."""
    return generate_grasps("cup", (NOMINAL_SCALE,), per_scale=16, batch_size=16, seed=0, nthread=1)


def test_hold_check_is_the_env_holding_still(tmp_path, cup_grasps):
    """A nominal env reset into each grasp and held still (zero action) tilts the cup exactly as far as the hold
    check says, and the grasps the check fails tip over, drop or sink the cup in the env."""
    rule = HoldRule.for_hand(DEFAULT_HAND)  # the default hand's nominal physics (on 'digit360': HoldRule())
    nominal = default_randomization(DEFAULT_HAND, enabled=False)
    assert (rule.friction, rule.mass) == (np.mean(nominal.friction), np.mean(nominal.mass))
    assert cup_grasps.hand == DEFAULT_HAND
    cup_grasps.save(tmp_path / "g.npz")
    saved = GraspCache.load(tmp_path / "g.npz")  # the rows the env starts from (stored as float32)
    worst = hold_check(saved, rule, batch_size=16, nthread=1)[0]
    fails = worst >= rule.max_tilt
    assert fails.sum() >= 2 and (~fails).sum() >= 8, worst  # this sample has both kinds, by a wide margin
    cfg = EnvConfig(object="cup", grasp_cache=str(tmp_path / "g.npz"), randomization=nominal)
    env = RotateCupVec(cfg, num_envs=64, seed=0, nthread=1)
    env.reset(seed=0)
    rows = saved.grasps[0, :, :16]
    row = np.array([np.flatnonzero(np.all(np.abs(rows - q) < 1e-9, axis=1))[0] for q in env.grasp_q])
    tilt, sank, ended = np.zeros(64), np.zeros(64), np.zeros(64, dtype=bool)
    z0 = env.start_pos[:, 2].copy()
    for _ in range(round(rule.seconds * cfg.control_hz)):
        _, _, term, _, info = env.step(np.zeros((64, 16)))
        tilt = np.where(ended, tilt, np.maximum(tilt, info["tilt"]))
        sank = np.where(ended, sank, np.maximum(sank, z0 - env.starts.qpos[:, env.obj_qpos + 2]))
        ended |= term
    assert len(set(row[fails[row]])) >= 2 and len(set(row[~fails[row]])) >= 5  # the env met both kinds
    held = ~fails[row]
    # the same tilt: to the last digits on the shipped physics; the hardware physics' contacts (elliptic cones,
    # noslip) carry the last-bit difference of the cup's geometry (the check compiles it at the largest scale, a
    # nominal env at its own) to some 1e-5 rad over 3 s
    np.testing.assert_allclose(tilt[held], worst[row[held]], atol=1e-4)
    assert not ended[held].any() and np.all(sank[held] < HOLD_DROP)
    assert np.all(ended[~held] | (tilt[~held] >= rule.max_tilt) | (sank[~held] > HOLD_DROP))


def test_a_slippery_surface_in_the_hold_check_is_the_evaluation_s_friction_condition(tmp_path):
    """The hold check at ``surface`` s tilts the cup exactly as a nominal env under the evaluation's friction
    condition x s held still (domes and links scaled together), and a quarter of the friction loses grasps that hold
    at the nominal surface."""
    cache = load_default_cache("cup")
    bucket = int(np.abs(cache.scales - NOMINAL_SCALE).argmin())
    nominal_rows = GraspCache("cup", cache.scales[bucket : bucket + 1], cache.grasps[bucket : bucket + 1, :24],
                              hand=cache.hand)
    nominal_rows.save(tmp_path / "g.npz")
    saved = GraspCache.load(tmp_path / "g.npz")
    rule = HoldRule.for_hand(DEFAULT_HAND)
    worst = hold_check(saved, replace(rule, surface=0.25), batch_size=24, nthread=1)[0]
    assert np.all(hold_check(saved, rule, batch_size=24, nthread=1)[0] < rule.max_tilt)  # all hold at x1
    assert (worst >= rule.max_tilt).sum() >= 3, worst  # and several fail at x0.25
    nominal = default_randomization(DEFAULT_HAND, enabled=False)
    cfg = EnvConfig(object="cup", grasp_cache=str(tmp_path / "g.npz"), randomization=nominal,
                    perturb=Perturbation(friction_scale=0.25))
    env = RotateCupVec(cfg, num_envs=32, seed=0, nthread=1)
    env.reset(seed=0)
    rows = saved.grasps[0, :, :16]
    row = np.array([np.flatnonzero(np.all(np.abs(rows - q) < 1e-9, axis=1))[0] for q in env.grasp_q])
    tilt, ended = np.zeros(32), np.zeros(32, dtype=bool)
    for _ in range(round(rule.seconds * cfg.control_hz)):
        _, _, term, _, info = env.step(np.zeros((32, 16)))
        tilt = np.where(ended, tilt, np.maximum(tilt, info["tilt"]))
        ended |= term
    held = worst[row] < rule.max_tilt
    assert held.sum() >= 3 and (~held).sum() >= 3  # the env met both kinds
    np.testing.assert_allclose(tilt[held], worst[row[held]], atol=1e-4)
    assert not ended[held].any()


def test_grasps_generated_for_a_slippery_surface_hold_a_slippery_cup_and_say_so(tmp_path):
    """`rotate grasps --hold-surface 0.25`: every kept grasp passes a fresh hold check at a quarter of the friction,
    the file records the surface as the rule's fifth number (a rule at the hand's own surface keeps four), and a
    cache loads with either."""
    from rotation.jobs import grasps as grasps_job

    rule = HoldRule.for_hand(DEFAULT_HAND, surface=0.25)
    assert len(HoldRule.for_hand(DEFAULT_HAND).as_array()) == 4 and list(rule.as_array())[4] == 0.25
    paths = grasps_job.run(grasps_job.Config(objects=("cup",), scales=(NOMINAL_SCALE,), per_scale=3, batch_size=16,
                                             hold_surface=0.25, out=tmp_path))
    cache = GraspCache.load(paths[0])
    assert cache.hold == tuple(rule.as_array())
    assert np.all(hold_check(cache, rule, batch_size=8, nthread=1) < rule.max_tilt)
    with pytest.raises(ValueError, match="hold_surface"):
        grasps_job.Config(hold_surface=0.0, out=tmp_path / "x")


def test_the_hold_rule_only_removes_grasps(tmp_path, cup_grasps):
    """With the rule, generation keeps, in order, the grasps of the same draws that pass it, records the rule in the
    file, and every kept grasp passes a fresh check."""
    rule = HoldRule.for_hand(DEFAULT_HAND)
    held = generate_grasps("cup", (NOMINAL_SCALE,), per_scale=6, batch_size=16, seed=0, nthread=1, hold=rule)
    passing = cup_grasps.grasps[0][hold_check(cup_grasps, rule, batch_size=16, nthread=1)[0] < rule.max_tilt]
    np.testing.assert_array_equal(held.grasps[0], passing[:6])
    assert np.all(hold_check(held, rule, batch_size=8, nthread=1) < rule.max_tilt)
    held.save(tmp_path / "h.npz")
    assert GraspCache.load(tmp_path / "h.npz").hold == (3.0, rule.friction, rule.mass, rule.max_tilt)
    assert cup_grasps.hold == ()


def test_a_damaged_hold_record_is_refused(tmp_path):
    np.savez(tmp_path / "hold.npz", object="cylinder", scales=small_cache().scales, grasps=small_cache().grasps,
             hold=np.array([3.0, np.nan]))
    with pytest.raises(ValueError, match=r"'hold' must be 4 or 5 finite numbers"):
        GraspCache.load(tmp_path / "hold.npz")


@pytest.mark.parametrize("obj", ["cup", "cup_small", "cup_large"])
def test_shipped_cup_caches_pass_the_hold_rule(obj):
    """The caches the policies are evaluated on were generated with the default HoldRule, and their grasps at the
    nominal scale hold the cup by themselves (the other scales were checked when they were generated)."""
    cache = load_default_cache(obj)
    rule = HoldRule.for_hand(DEFAULT_HAND)  # what `rotate grasps` checks with on the default hand
    assert cache.hand == DEFAULT_HAND and cache.hold == tuple(rule.as_array())
    bucket = int(np.abs(cache.scales - NOMINAL_SCALE).argmin())
    nominal = GraspCache(obj, cache.scales[bucket : bucket + 1], cache.grasps[bucket : bucket + 1])
    assert np.all(hold_check(nominal, rule) < rule.max_tilt)


def test_a_cache_write_that_fails_leaves_nothing_behind(tmp_path, monkeypatch):
    """A full disk while saving: the error reaches the caller, no partial cache (nor its temporary file) is left,
    and an earlier cache at the path is kept as it was."""
    import envs.grasp_cache as gc

    cache = load_default_cache("cup")
    path = tmp_path / "grasps_cup.npz"
    cache.save(path)
    before = path.read_bytes()

    def full_disk(f, **arrays):
        f.write(b"PK\x03\x04 half a zip")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(gc.np, "savez_compressed", full_disk)
    with pytest.raises(OSError, match="No space left"):
        cache.save(path)
    with pytest.raises(OSError, match="No space left"):
        cache.save(tmp_path / "new.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grasps_cup.npz"] and path.read_bytes() == before
