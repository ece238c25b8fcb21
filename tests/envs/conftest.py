"""Shared helpers of the env tests."""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np
import pytest


def _touching(sim, body: str, ignore: tuple[str, ...] = ()) -> dict[str, float]:
    """{name of each geom touching ``body`` (of a body not named ``ignore``*): its summed normal force (N)}."""
    m, d, own, wrench, out = sim.model, sim.data, sim.model.body(body).id, np.zeros(6), {}
    for i in range(d.ncon):
        con = d.contact[i]
        if own not in (m.geom_bodyid[con.geom1], m.geom_bodyid[con.geom2]):
            continue
        other = con.geom2 if m.geom_bodyid[con.geom1] == own else con.geom1
        if ignore and m.body(m.geom_bodyid[other]).name.startswith(ignore):
            continue
        mujoco.mj_contactForce(m, d, i, wrench)
        out[m.geom(other).name] = out.get(m.geom(other).name, 0.0) + wrench[0]
    return out


@pytest.fixture(scope="session")
def touching() -> Callable[..., dict[str, float]]:
    """``touching(sim, "plug")``: what touches a held object now, geom by geom, and how hard (N)."""
    return _touching
