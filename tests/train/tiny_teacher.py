"""The tiny teacher run the teacher tests train (a plain module: pytest collects nothing here)."""

from __future__ import annotations

from rotation.train import teacher


def tiny_config(tmp_path, **kw) -> teacher.Config:
    """32 envs, 2,048 steps, checkpoints every 1,024, episodes of 50 steps, in tmp_path/run; ``kw`` overrides."""
    base = dict(out=tmp_path / "run", num_envs=32, n_steps=32, batch_size=256, n_epochs=4, total_steps=2048,
                checkpoint_every=1024, episode_steps=50, progress=False, seed=0, log_std_init=0.0)
    base.update(kw)
    return teacher.Config(**base)
