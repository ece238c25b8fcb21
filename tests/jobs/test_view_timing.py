"""`rotate view` acts at the control rate and action scale of the bundle it shows (what the policy was trained at)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from rotation.jobs import view
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def slow_bundle(tmp_path_factory) -> str:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("view") / "slow_student"
    PolicyBundle(BundleConfig(latent_source="adaptation", control_hz=10.0, action_scale=0.2)).save(path)
    return str(path)


def test_the_env_runs_at_the_bundles_rate_and_scale(tmp_path, monkeypatch, slow_bundle):
    seen = {}

    class Built(Exception):
        pass

    def capture(cfg, **kwargs):
        seen["cfg"] = cfg
        raise Built

    monkeypatch.setattr(view, "RotateCupVec", capture)
    with pytest.raises(Built):
        view.run(view.Config(out=tmp_path / "v.mp4", policy=slow_bundle, steps=2))
    assert (seen["cfg"].control_hz, seen["cfg"].action_scale) == (10.0, 0.2)
    with pytest.raises(Built):  # 'random' has no bundle: the env's defaults
        view.run(view.Config(out=tmp_path / "v.mp4", policy="random", steps=2))
    assert (seen["cfg"].control_hz, seen["cfg"].action_scale) == (20.0, 1 / 24)


def test_video_frames_are_the_bundles_steps(tmp_path, slow_bundle):
    """End to end, headless (a fresh process so MUJOCO_GL applies): one GIF frame per 10 Hz policy step."""
    out = tmp_path / "slow.gif"
    cmd = [sys.executable, "-m", "rotation.cli", "view", "--out", str(out), "--policy", slow_bundle, "--steps", "3",
           "--width", "64", "--height", "64"]
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    from PIL import Image, ImageSequence

    with Image.open(out) as gif:  # Pillow merges identical frames and adds up their durations
        total_ms = sum(frame.info["duration"] for frame in ImageSequence.Iterator(gif))
    assert total_ms == pytest.approx(4 * 100.0)  # the start frame and 3 steps, 100 ms each at 10 Hz


def test_a_tactile_adapter_refreshes_and_smooths_as_in_evaluate(monkeypatch):
    """A video of a tactile adapter acts with its corrections as evaluate does (no delay): refreshed every
    touch_every steps, averaged by the bundle's touch_smoothing."""
    import numpy as np

    from rotation.evaluate import rollout

    class Adapter:
        touch_every, touch_smoothing = 2, 0.5
        config = BundleConfig(latent_source="adaptation")
        acted: list[float] = []

        def start_correction(self, step):
            return None  # no cautious start

        def act_batch(self, groups, correction=None):
            self.acted.append(float(correction[0, 0]))
            return np.zeros((1, 16), np.float32)

    reads = iter([2.0, 4.0, 6.0])
    monkeypatch.setattr(rollout, "touch_correction",
                        lambda policy, obs, groups: np.full((1, policy.config.latent_dim), next(reads), np.float32))
    policy = Adapter()
    act = view._actor(view.Config(policy="x", seed=3), policy)
    obs = {key: np.zeros((1, 1)) for key in policy.config.obs_groups}
    for _ in range(6):
        act(obs)
    assert policy.acted == [2.0, 2.0, 3.0, 3.0, 4.5, 4.5]
