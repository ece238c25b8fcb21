"""Offscreen rendering: `import envs` chooses EGL on Linux before MuJoCo picks its OpenGL platform (a headless
machine would otherwise get GLFW and fail without a display), and a machine without a working platform gets one
line saying what failed and what to install (envs.render.offscreen_renderer), not MuJoCo's traceback."""

from __future__ import annotations

import os
import subprocess
import sys

import mujoco
import pytest

from envs.errors import JobFailed
from envs.render import offscreen_renderer


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="EGL is the default on Linux only")
def test_import_envs_chooses_egl_before_mujoco_is_imported_and_keeps_a_users_choice():
    code = "import envs, os, mujoco; print(os.environ['MUJOCO_GL'])"
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "egl"
    env["MUJOCO_GL"] = "osmesa"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "osmesa"


def test_a_failing_opengl_platform_is_one_line_naming_what_needed_it(monkeypatch):
    def no_gl(*args, **kwargs):
        raise mujoco.FatalError("an OpenGL platform library has not been loaded into this process\nmore")

    monkeypatch.setattr(mujoco, "Renderer", no_gl)
    with pytest.raises(JobFailed) as err:
        offscreen_renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 24, 32, "the wrist camera")
    message = str(err.value)
    assert "\n" not in message and message.startswith("the wrist camera needs MuJoCo's offscreen OpenGL")
    assert "MUJOCO_GL=" in message and "libegl1" in message
