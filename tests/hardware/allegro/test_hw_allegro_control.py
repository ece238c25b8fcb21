"""Allegro host-side control on hand-made frames: cycle assembly after lost frames, velocity filter, PD law."""

from __future__ import annotations

import numpy as np
import pytest

from rotation.hardware.allegro.control import AllegroConfig, CycleAssembler, VelocityFilter, pd_torque


def frames(tick: int) -> list[tuple[int, np.ndarray]]:
    """The four frames of hand tick ``tick``: finger f's joints all read tick + f / 10."""
    return [(f, np.full(4, tick + f / 10)) for f in range(4)]


def feed(asm: CycleAssembler, seq) -> list[np.ndarray]:
    return [q for f, q4 in seq if (q := asm.add(f, q4)) is not None]


def test_complete_cycles():
    asm = CycleAssembler()
    out = feed(asm, frames(0) + frames(1))
    assert len(out) == 2 and np.allclose(out[1][12:], 1.3) and asm.incomplete == 0


@pytest.mark.parametrize("lost", [0, 1, 3])
def test_lost_frame_skips_one_cycle_without_mixing_ticks(lost):
    asm = CycleAssembler()
    tick1 = [fr for fr in frames(1) if fr[0] != lost]
    out = feed(asm, frames(0) + tick1 + frames(2) + frames(3))
    assert asm.incomplete == 1
    assert len(out) == 3
    for q, tick in zip(out, (0, 2, 3), strict=True):  # every cycle holds one tick only
        assert np.allclose(np.floor(q), tick)


def test_velocity_filter_ema():
    vf = VelocityFilter(smoothing=0.5, nominal_dt=0.003)
    assert np.all(vf.update(np.zeros(16), 0.003) == 0)
    v = vf.update(np.full(16, 0.003), 0.003)  # raw 1 rad/s, half of it after one EMA step
    assert np.allclose(v, 0.5)
    v = vf.update(np.full(16, 0.006), 0.0)  # a burst (dt ~ 0) is floored at 0.25 x nominal
    assert np.allclose(v, 0.5 * 0.5 + 0.5 * 4.0)


def test_pd_torque_hand_computed():
    tau = pd_torque(np.array([0.1]), np.array([2.0]), np.array([0.3]), kp=3.0, kd=0.1)
    assert tau == pytest.approx([3.0 * 0.2 - 0.1 * 2.0])


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="velocity_smoothing"):
        AllegroConfig(velocity_smoothing=1.0)
    with pytest.raises(ValueError, match="feedback_timeout_s"):
        AllegroConfig(feedback_timeout_s=0.004)
    with pytest.raises(ValueError, match="hand_id"):
        AllegroConfig(hand_id=4)
