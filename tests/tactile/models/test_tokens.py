"""The token interface encoders declare: validation, spans, checks of encoder outputs, normalized concatenation."""

from __future__ import annotations

import pytest
import torch

from rotation.tactile.models.tokens import TokenInterface

IFACE = TokenInterface((("img", 3), ("imu", 2)), width=4)


def test_names_counts_total_slices():
    assert IFACE.names == ("img", "imu") and IFACE.counts == {"img": 3, "imu": 2} and IFACE.total == 5
    assert IFACE.slices() == {"img": slice(0, 3), "imu": slice(3, 5)}


@pytest.mark.parametrize("groups, width, match", [
    ((), 4, "at least one"), ((("a", 1), ("a", 2)), 4, "repeat"), ((("a", 0),), 4, "count > 0"),
    ((("a", 1),), 0, "width"),
])
def test_bad_interfaces(groups, width, match):
    with pytest.raises(ValueError, match=match):
        TokenInterface(groups, width)


def test_check_and_concat():
    tokens = {"img": 5.0 + 3.0 * torch.randn(2, 3, 4), "imu": torch.randn(2, 2, 4)}
    assert IFACE.check(tokens) == 2
    flat = IFACE.concat(tokens)
    assert flat.shape == (2, 5, 4)
    assert torch.allclose(flat[:, IFACE.slices()["img"]].mean(-1), torch.zeros(2, 3), atol=1e-5)  # layer-normed
    assert torch.equal(IFACE.concat(tokens, normalize=False)[:, 3:], tokens["imu"])
    masked = {"img": tokens["img"][:, :1], "imu": tokens["imu"]}
    assert IFACE.check(masked, partial=True) == 2 and IFACE.concat(masked).shape == (2, 3, 4)
    with pytest.raises(ValueError, match=r"tokens\['img'\]: expected \(B, 3, 4\)"):
        IFACE.check(masked)
    with pytest.raises(ValueError, match="expected groups"):
        IFACE.check({"img": tokens["img"]})
    with pytest.raises(ValueError, match="batch"):
        IFACE.check({"img": tokens["img"], "imu": tokens["imu"][:1]})
    with pytest.raises(ValueError, match=r"\(B, 1..2, 4\)"):
        IFACE.check({"img": tokens["img"], "imu": torch.randn(2, 2, 5)}, partial=True)
