"""Headless rendering (MuJoCo offscreen; `import envs` sets MUJOCO_GL=egl on Linux unless it is set)."""

from __future__ import annotations

import os

import mujoco
import numpy as np

from envs.errors import JobFailed


def offscreen_renderer(model: mujoco.MjModel, height: int, width: int, what: str = "rendering"
                       ) -> mujoco.Renderer:
    """A mujoco.Renderer of ``model``; JobFailed in one line (what needs it, why, what to try) when the machine
    has no working OpenGL platform for MuJoCo."""
    try:
        return mujoco.Renderer(model, height=height, width=width)
    except Exception as err:  # MuJoCo raises FatalError, RuntimeError or an OpenGL error here
        platform = os.environ.get("MUJOCO_GL", "(unset)")
        raise JobFailed(f"{what} needs MuJoCo's offscreen OpenGL, which failed with MUJOCO_GL={platform} "
                        f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); install the "
                        "platform's library (EGL: libegl1; OSMesa: libosmesa6) or set MUJOCO_GL to one that "
                        "works here") from err


def render_frame(renderer: mujoco.Renderer, core, i: int = 0, camera: str = "front") -> np.ndarray:
    """RGB frame (H, W, 3) uint8 of simulation i of a RotateCupVec, from a named camera."""
    model, data = core.get_data(i)
    mujoco.mj_forward(model, data)
    renderer._model = model  # per-simulation sizes (object scale) come from this sim's model
    renderer.update_scene(data, camera=camera)
    return renderer.render()
