"""Headless rendering of the batched env (MuJoCo offscreen; set MUJOCO_GL=egl on machines without a display)."""

from __future__ import annotations

import mujoco
import numpy as np


def render_frame(renderer: mujoco.Renderer, core, i: int = 0, camera: str = "front") -> np.ndarray:
    """RGB frame (H, W, 3) uint8 of simulation i of a RotateCupVec, from a named camera."""
    model, data = core.get_data(i)
    mujoco.mj_forward(model, data)
    renderer._model = model  # per-simulation sizes (object scale) come from this sim's model
    renderer.update_scene(data, camera=camera)
    return renderer.render()
