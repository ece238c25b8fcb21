"""Evaluation videos: the first episode of each policy in one condition, side by side, as an MP4.

MuJoCo renders offscreen; on a machine without a display set ``MUJOCO_GL=egl`` (or ``osmesa``) before Python
starts (the Makefile exports it).
"""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np

from envs.core import RotateCupVec
from envs.render import offscreen_renderer, render_frame


class FrameRecorder:
    """Renders simulation 0 of ``env`` into one frame list per policy label."""

    def __init__(self, env: RotateCupVec, width: int = 320, height: int = 240, camera: str = "front") -> None:
        self.renderer = offscreen_renderer(env.model, height, width, "--video")
        self.camera = camera
        self.frames: dict[str, list[np.ndarray]] = {}

    def hook(self, label: str):
        """A callback ``f(env)`` that appends the current frame of simulation 0 to ``label``'s list."""
        frames = self.frames.setdefault(label, [])
        return lambda env: frames.append(render_frame(self.renderer, env, 0, camera=self.camera))

    def write(self, path: Path, fps: int) -> Path:
        """Tile the policies left to right (each labelled), hold each one's last frame until the longest ends."""
        path.parent.mkdir(parents=True, exist_ok=True)
        labels = list(self.frames)
        length = max(len(f) for f in self.frames.values())
        with imageio.get_writer(path, fps=fps, macro_block_size=1) as writer:
            for t in range(length):
                tiles = [_label(self.frames[k][min(t, len(self.frames[k]) - 1)], k) for k in labels]
                writer.append_data(np.concatenate(tiles, axis=1))  # (H, W * P, 3)
        return path

    def close(self) -> None:
        self.renderer.close()


def _label(frame: np.ndarray, text: str) -> np.ndarray:
    """Write ``text`` in the top-left corner of an (H, W, 3) uint8 frame."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img)
    draw.rectangle([0, 0, 8 + 7 * len(text), 16], fill=(0, 0, 0))
    draw.text((4, 2), text, fill=(255, 255, 255))
    return np.asarray(img)
