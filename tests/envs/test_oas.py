"""Object-action-surface (envs.oas): the surface faces the held object and only it, each action moves the wrist as
described, an episode is deterministic per seed, and what the object touches reaches the fingertips."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.grasp_cache import load_default_cache
from envs.oas import ACTIONS, GAP, OBJECTS, SETTLE_S, SURFACES, OasConfig, OasSim, draw_episode


@pytest.fixture(scope="module")
def grasps():
    return load_default_cache("cup", "", "digit360_v4")


def test_the_actions_move_the_wrist_as_described(grasps):
    cfg = OasConfig()
    for action in ACTIONS:
        ep = draw_episode(cfg, 5, grasps, "plastic", action, "flat")
        sim = OasSim(cfg, ep, grasps)
        ts = np.arange(0.0, cfg.duration_s, 0.002)
        pos = np.array([sim._wrist(t)[0] for t in ts])
        assert np.all(pos[ts <= SETTLE_S] == 0)  # still while the object settles
        assert pos[:, 2].max() == pytest.approx(GAP + ep.depth, abs=2e-5)  # reaches past contact by the depth
        lateral = np.linalg.norm(pos[:, :2], axis=1).max()
        if action == "slide":
            assert lateral == pytest.approx(ep.extent, rel=0.01)
        elif action == "rotate":  # the wrist swings about the object's axis by the extent
            quats = np.array([sim._wrist(t)[1] for t in ts])
            turned = 2 * np.degrees(np.arccos(np.clip(np.abs(quats @ sim._palm_quat0), -1, 1))).max()
            assert turned == pytest.approx(math.degrees(ep.extent), rel=0.02) and lateral > 0
        else:
            assert lateral == 0
        if action == "tap":  # up and down at its frequency
            crossings = np.flatnonzero(np.diff((pos[:, 2] > (GAP + ep.depth) / 2).astype(int)) == 1)
            assert np.mean(np.diff(crossings)) * 0.002 == pytest.approx(1 / ep.frequency, rel=0.05)


def test_an_episode_is_deterministic_and_the_surface_contact_reaches_the_fingertips(grasps):
    cfg = OasConfig(duration_s=1.5)
    ep = draw_episode(cfg, 2, grasps, "rubber", "press", "flat")
    a, b = OasSim(cfg, ep, grasps).run(), OasSim(cfg, ep, grasps).run()
    assert np.array_equal(a.contact, b.contact) and np.array_equal(a.surface_force, b.surface_force)
    assert a.held
    settle = int(SETTLE_S / 0.002)
    assert a.surface_force[:settle].max() == 0  # the surface is placed above the settled object: no contact yet
    pressed = a.surface_force > 0.5
    assert pressed.any()
    # while the surface presses the object into the hand, the fingertips holding it feel more normal force
    normal = a.contact[:, :, 0].sum(axis=0)
    assert normal[pressed].mean() > normal[settle:][~pressed[settle:]].mean()


def test_draws_cover_every_label_and_bad_names_are_refused(grasps):
    cfg = OasConfig()
    eps = [draw_episode(cfg, s, grasps) for s in range(120)]
    assert {e.object for e in eps} == set(OBJECTS) and {e.action for e in eps} == set(ACTIONS)
    assert {e.surface for e in eps} == set(SURFACES)
    assert eps[3].labels == {"object": list(OBJECTS).index(eps[3].object), "action": ACTIONS.index(eps[3].action),
                             "surface": SURFACES.index(eps[3].surface)}
    with pytest.raises(ValueError, match="unknown surface"):
        draw_episode(cfg, 0, grasps, surface="glass")
    with pytest.raises(ValueError, match="Digit 360"):
        OasConfig(hand="xela_v4")
