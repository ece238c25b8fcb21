"""envs.hand_model against the vendor's published kinematics of the right Allegro V4 and Meta's Digit 360 mount.

The table below is typed from the published figures (docs/reference/hora.md, "Allegro hand facts": the vendor's
allegro_hand_description, repeated by Hora's allegro.urdf and MuJoCo Menagerie's wonik_allegro), independently of
envs.allegro_description, and chained here with plain numpy (URDF convention: child = parent * translate(xyz) *
rot(rpy) * rot(axis, q)). The model must put every joint's anchor within 1 mm and its axis within 1 degree of this
chain at random configurations, and each Digit 360 dome centre within 2 mm of Meta's mount.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from envs import constants as C
from envs.hand_model import SEGMENTS, hand_xml

VENDOR: dict[str, tuple[str, tuple, tuple, tuple]] = {
    # joint: (parent joint or palm, origin xyz (m), origin rpy (rad), axis in the joint's frame)
    "index_0": ("palm", (0.0, 0.0435, -0.001542), (-0.0873, 0.0, 0.0), (0, 0, 1)),
    "middle_0": ("palm", (0.0, 0.0, 0.0007), (0.0, 0.0, 0.0), (0, 0, 1)),
    "ring_0": ("palm", (0.0, -0.0435, -0.001542), (0.0873, 0.0, 0.0), (0, 0, 1)),
    "thumb_0": ("palm", (-0.0182, 0.019333, -0.045987), (0.0, -1.658063, -1.570796), (-1, 0, 0)),
    "thumb_1": ("thumb_0", (-0.027, 0.005, 0.0399), (0.0, 0.0, 0.0), (0, 0, 1)),
    "thumb_2": ("thumb_1", (0.0, 0.0, 0.0177), (0.0, 0.0, 0.0), (0, 1, 0)),
    "thumb_3": ("thumb_2", (0.0, 0.0, 0.0514), (0.0, 0.0, 0.0), (0, 1, 0)),
}
for _f in ("index", "middle", "ring"):
    VENDOR[f"{_f}_1"] = (f"{_f}_0", (0.0, 0.0, 0.0164), (0.0, 0.0, 0.0), (0, 1, 0))
    VENDOR[f"{_f}_2"] = (f"{_f}_1", (0.0, 0.0, 0.054), (0.0, 0.0, 0.0), (0, 1, 0))
    VENDOR[f"{_f}_3"] = (f"{_f}_2", (0.0, 0.0, 0.0384), (0.0, 0.0, 0.0), (0, 1, 0))
DOME_PAST_LAST_JOINT = {"index": 0.057, "middle": 0.057, "ring": 0.057, "thumb": 0.0723}
"""Meta's Digit 360 on the Allegro: the sensor's base 20 mm (thumb 35.3 mm) past the last joint, its dome's centre
about 37 mm further (m)."""
PALM_UP = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
"""The vendor's palm frame in the env's world: fingers (+z) along world +x, palm normal (+x) up."""


def _rpy(r: float, p: float, y: float) -> np.ndarray:
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _about(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def vendor_chain(q: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """joint -> (anchor (3,), axis (3,), the rotation of the link it moves (3, 3)), world frame."""
    frames = {"palm": (PALM_UP, np.zeros(3))}
    out = {}
    for name in C.JOINT_NAMES:  # parents come before children in bus order
        parent, xyz, rpy, axis = VENDOR[name]
        rot_p, pos_p = frames[parent]
        rot = rot_p @ _rpy(*rpy)
        pos = pos_p + rot_p @ np.asarray(xyz)
        link = rot @ _about(axis, q[C.JOINT_NAMES.index(name)])
        frames[name] = (link, pos)
        out[name] = (pos, rot @ np.asarray(axis, dtype=float), link)
    return out


@pytest.fixture(scope="module")
def hand():
    model = mujoco.MjModel.from_xml_string(hand_xml())
    return model, mujoco.MjData(model)


def _pose(model, data, q: np.ndarray) -> None:
    for i, name in enumerate(C.JOINT_NAMES):
        data.qpos[model.joint(name).qposadr[0]] = q[i]
    mujoco.mj_kinematics(model, data)


def test_joint_anchors_and_axes_follow_the_vendors_kinematics(hand):
    model, data = hand
    rng = np.random.default_rng(300)
    worst_mm, worst_deg = 0.0, 0.0
    for _ in range(300):
        q = rng.uniform(C.JOINT_LOWER, C.JOINT_UPPER)
        _pose(model, data, q)
        for name, (anchor, axis, _) in vendor_chain(q).items():
            j = model.joint(name).id
            worst_mm = max(worst_mm, 1000 * float(np.linalg.norm(data.xanchor[j] - anchor)))
            worst_deg = max(worst_deg, float(np.degrees(np.arccos(np.clip(data.xaxis[j] @ axis, -1, 1)))))
    assert worst_mm < 1.0 and worst_deg < 1.0, (worst_mm, worst_deg)


def test_joint_0_rolls_the_finger_about_its_long_axis(hand):
    """On the real hand joint 0 turns a finger about its own length: a straight finger only twists (its tip stays),
    a flexed one sweeps sideways."""
    model, data = hand
    straight = np.clip(np.zeros(16), C.JOINT_LOWER, C.JOINT_UPPER)
    for flexed, moves in ((0.0, False), (1.2, True)):
        q = straight.copy()
        q[[1, 5, 9]] = flexed
        _pose(model, data, q)
        before = data.site("middle_tip").xpos.copy()
        q[4] = 0.4
        _pose(model, data, q)
        shift = float(np.linalg.norm(data.site("middle_tip").xpos - before))
        assert (shift > 0.02) if moves else (shift < 1e-6), (flexed, shift)


def test_digit360_domes_sit_at_metas_mount(hand):
    model, data = hand
    rng = np.random.default_rng(7)
    for _ in range(50):
        q = rng.uniform(C.JOINT_LOWER, C.JOINT_UPPER)
        _pose(model, data, q)
        chain = vendor_chain(q)
        for finger in C.FINGERS:
            anchor, _, link = chain[f"{finger}_3"]
            want = anchor + link @ np.array([0.0, 0.0, DOME_PAST_LAST_JOINT[finger]])
            assert np.linalg.norm(data.site(f"{finger}_tip").xpos - want) < 0.002, finger
            assert np.linalg.norm(data.geom(f"{finger}_tip").xpos - want) < 0.002, finger
            assert abs(model.geom(f"{finger}_tip").size[0] - 0.012) < 1e-9


def test_moving_one_joint_moves_only_what_it_carries(hand):
    """Joint j moves the geoms and sites of its own link and of the links past it, and nothing else."""
    model, data = hand
    q0 = (C.JOINT_LOWER + C.JOINT_UPPER) / 2
    _pose(model, data, q0)
    geoms0, sites0 = data.geom_xpos.copy(), data.site_xpos.copy()
    for j, name in enumerate(C.JOINT_NAMES):
        finger, k = name.rsplit("_", 1)
        carried = {model.body(f"{finger}_{seg}").id for seg in SEGMENTS[int(k):]}
        q = q0.copy()
        q[j] += 0.2
        _pose(model, data, q)
        for g in range(model.ngeom):
            moved = np.linalg.norm(data.geom_xpos[g] - geoms0[g]) > 1e-9
            on_it = model.geom_bodyid[g] in carried
            if not on_it:
                assert not moved, (name, model.geom(g).name)
        for s in range(model.nsite):
            if model.site_bodyid[s] not in carried:
                assert np.allclose(data.site_xpos[s], sites0[s]), (name, model.site(s).name)
        assert np.linalg.norm(data.site(f"{finger}_tip").xpos - sites0[model.site(f"{finger}_tip").id]) > 1e-4


def test_limits_boxes_and_masses_are_the_published_ones(hand):
    model, _ = hand
    for j, name in enumerate(C.JOINT_NAMES):
        assert np.allclose(model.joint(name).range, [C.JOINT_LOWER[j], C.JOINT_UPPER[j]])
        assert np.allclose(model.actuator(C.ACTUATOR_NAMES[j]).ctrlrange, [C.JOINT_LOWER[j], C.JOINT_UPPER[j]])
    # full sizes (m): finger links 19.6 x 27.5 mm in cross-section, the palm 40.8 x 113 x 95 mm
    assert np.allclose(2 * model.geom("index_proximal").size, [0.0196, 0.0275, 0.054])
    assert np.allclose(2 * model.geom("thumb_medial").size, [0.0196, 0.0275, 0.0514])
    assert np.allclose(2 * model.geom("palm").size, [0.0408, 0.1130, 0.095])
    assert np.isclose(model.body("palm").mass[0], 0.415)
    assert np.isclose(model.body("index_proximal").mass[0], 0.065)
    assert np.isclose(model.body("thumb_base").mass[0], 0.0176)


def test_the_open_and_home_poses_touch_nothing(hand):
    model, data = hand
    for q in (np.clip(np.zeros(16), C.JOINT_LOWER, C.JOINT_UPPER), C.HOME_POSE):
        _pose(model, data, q)
        mujoco.mj_collision(model, data)
        assert data.ncon == 0, [(model.geom(c.geom1).name, model.geom(c.geom2).name) for c in data.contact[:data.ncon]]


def test_the_vendor_hand_is_an_env_variant_with_its_own_grasps():
    """EnvConfig(hand='digit360_v4') builds this model, starts from its own shipped cup grasps (generated around its
    own canonical pose and object centre), and steps; its Digit 360 touch works, the Xela hand's does not."""
    from envs.config import EnvConfig
    from envs.core import RotateCupVec
    from envs.grasp_cache import load_default_cache
    from envs.scene import hand_variant

    cache = load_default_cache("cup", hand="digit360_v4")
    assert cache.hand == "digit360_v4" and cache.hold  # generated with the hold check
    centres = cache.grasps[..., C.NUM_JOINTS : C.NUM_JOINTS + 3].reshape(-1, 3)
    assert np.linalg.norm(centres.mean(axis=0) - hand_variant("digit360_v4").object_start) < 0.03
    env = RotateCupVec(EnvConfig(hand="digit360_v4"), num_envs=2, seed=0, nthread=1)
    assert env.model.nbody == mujoco.MjModel.from_xml_string(hand_xml()).nbody + 1  # the hand and the cup
    obs = env.reset(seed=1)
    for _ in range(3):
        obs, *_ = env.step(np.zeros((2, 16), dtype=np.float32))
    assert all(np.all(np.isfinite(v)) for v in obs.values() if isinstance(v, np.ndarray))
    assert EnvConfig(hand="digit360_v4", tactile=True).tactile  # its 12 mm domes render (tests/envs/test_digit360.py)
    with pytest.raises(ValueError, match="tactile"):
        EnvConfig(hand="xela_v4", tactile=True)


# ---------------------------------------------------------------------------------------- the Xela variant (xela_v4)
@pytest.fixture(scope="module")
def xela_hand():
    from envs.scene import hand_spec

    model = hand_spec("xela_v4").compile()
    return model, mujoco.MjData(model)


def test_the_xela_variant_shares_the_kinematics_and_carries_stock_length_tips(xela_hand):
    """The same description builds both variants: every joint where the Digit 360 model has it, the stock tip's
    place (26.7 mm past a finger's last joint, 42.3 mm past the thumb's: the vendor's figures) inside the Xela shell."""
    from envs.sensors.xela import TIP_LENGTH, TIP_RADIUS, V4_TIP_START

    model, data = xela_hand
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.uniform(C.JOINT_LOWER, C.JOINT_UPPER)
        _pose(model, data, q)
        chain = vendor_chain(q)
        for name in C.JOINT_NAMES:
            assert np.linalg.norm(data.joint(name).xanchor - chain[name][0]) < 1e-3, name
        for finger in C.FINGERS:
            kind = "thumb" if finger == "thumb" else "finger"
            link_rot = chain[f"{finger}_3"][2]
            centre = chain[f"{finger}_3"][0] + link_rot @ [0, 0, V4_TIP_START[kind] + TIP_LENGTH - TIP_RADIUS]
            assert np.linalg.norm(data.site(f"{finger}_tip").xpos - centre) < 1e-3, finger
            stock = chain[f"{finger}_3"][0] + link_rot @ [0, 0, {"finger": 0.0267, "thumb": 0.0423}[kind]]
            assert np.linalg.norm(data.site(f"{finger}_tip").xpos - stock) < TIP_RADIUS  # the stock tip is inside


def test_xela_pads_lie_on_the_palmar_faces_of_their_links(xela_hand):
    """Every flat pad's outer face sits 2 mm (its thickness less 1 mm overlap) off its link's palmar face (+x in the
    vendor's link frames) or on the palm's, its normal along that face's, within the link's length."""
    from envs.sensors.xela import PADS, taxel_layout

    model, _ = xela_hand
    lay = taxel_layout("xela_v4")
    for p, pad in enumerate(PADS):
        body = lay.pad_body[p]
        rot, pos = lay.pad_rot[p], lay.pad_pos[p]
        assert np.allclose(rot[:, 2], [1, 0, 0]) and np.allclose(rot[:, 0], [0, 0, 1]), pad.name
        box = next(g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body(body).id
                   and model.geom(g).name == (body if body != "palm" else "palm"))
        centre, half = model.geom_pos[box], model.geom_size[box]
        if pad.kind == "fingertip":
            continue
        face = centre[0] + half[0]
        assert 0.0015 < pos[0] - face < 0.0031, (pad.name, pos[0] - face)
        length = pad.size[0] / 2
        assert centre[2] - half[2] - 1e-9 <= pos[2] - length and pos[2] + length <= centre[2] + half[2] + 1e-9, \
            pad.name


def test_moving_one_joint_moves_only_the_taxels_on_its_links(xela_hand):
    """Joint j moves the pads (and so every taxel) on its own link and on the links past it, and no other pad."""
    from envs.sensors.xela import PADS
    from envs.sensors.xela_hand import pad_site

    model, data = xela_hand
    q0 = (C.JOINT_LOWER + C.JOINT_UPPER) / 2
    _pose(model, data, q0)
    pads = [model.site(pad_site(p)).id for p in PADS]
    before = data.site_xpos[pads].copy(), data.site_xmat[pads].copy()
    for j, name in enumerate(C.JOINT_NAMES):
        finger, k = name.rsplit("_", 1)
        carried = {model.body(f"{finger}_{seg}").id for seg in SEGMENTS[int(k):]}
        q = q0.copy()
        q[j] += 0.2
        _pose(model, data, q)
        for i, s in enumerate(pads):
            moved = not (np.allclose(data.site_xpos[s], before[0][i]) and np.allclose(data.site_xmat[s], before[1][i]))
            assert moved == (model.site_bodyid[s] in carried), (name, PADS[i].name)
