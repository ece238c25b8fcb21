"""scripts/cautious_start.py: a student whose latent is shifted toward slippery cups over its first control steps.
The shift is the teacher's, computed from the friction alone; the bundle keeps it and its length; evaluation acts
with the shift over exactly the first steps of every episode (held to a reference computed here from the student's
networks), and a bad shift is refused when the bundle is built."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from envs.config import EnvConfig, default_randomization
from envs.constants import DEFAULT_HAND
from envs.core import RotateCupVec
from rotation.bundles import load_bundle
from rotation.evaluate.rollout import run_episodes
from rotation.evaluate.suites import get_suite
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleError

STEPS = 5


@pytest.fixture(scope="module")
def cautious_dir(load_script, tmp_path_factory):
    script = load_script("cautious_start")
    out = tmp_path_factory.mktemp("cautious") / "student"
    script.run(script.Config(steps=STEPS, calibration_envs=16, calibration_seed=123, out=out))
    return out


@pytest.fixture(scope="module")
def cautious(cautious_dir) -> PolicyBundle:
    return load_bundle(cautious_dir)


def test_the_bundle_keeps_the_teachers_slippery_shift_and_its_length(cautious, cautious_dir, load_script):
    cfg = cautious.config
    assert cfg.start_steps == STEPS and len(cfg.start_shift) == cfg.latent_dim
    card = cfg.card["cautious_start"]
    assert card["steps"] == STEPS and card["calibration_seed"] == 123 and "scripts/cautious_start.py" in card["command"]
    # the teacher's z moves toward slippery cups along the shift: recomputed by hand on the same starts
    teacher = load_bundle("teacher")
    env = RotateCupVec(EnvConfig(hand=DEFAULT_HAND, randomization=default_randomization(DEFAULT_HAND)), num_envs=16,
                       seed=123, nthread=1)
    obs = env.reset(seed=123)
    env.close()
    priv = obs["priv"].copy()
    priv[:, 5] *= 0.25  # envs.constants.PRIV_FIELDS: friction is the sixth field
    by_hand = (teacher.latent({"proprio": obs["proprio"], "priv": priv})
               - teacher.latent({"proprio": obs["proprio"], "priv": obs["priv"]})).mean(axis=0)
    np.testing.assert_allclose(cfg.start_shift, by_hand, rtol=1e-5, atol=1e-6)
    assert np.abs(by_hand).max() > 0.1  # a quarter of the friction moves the teacher's z
    np.testing.assert_array_equal(cautious.start_correction(0), np.float32(cfg.start_shift))
    assert cautious.start_correction(STEPS - 1) is not None and cautious.start_correction(STEPS) is None
    assert load_bundle("student").start_correction(0) is None  # the shipped student: no shift
    script = load_script("cautious_start")
    with pytest.raises(ValueError, match="already holds a bundle"):
        script.run(script.Config(steps=STEPS, out=cautious_dir))


class Reference:
    """The student on its latent plus ``shift`` for the first ``steps`` actions after each reset, by hand."""

    def __init__(self, env: RotateCupVec, student: PolicyBundle, shift, steps: int) -> None:
        self.student, self.shift, self.steps, self.k = student, torch.tensor(shift, dtype=torch.float32), steps, 0
        self.config = student.config
        reset = env.reset

        def counted(*args, **kwargs):
            self.k = 0
            return reset(*args, **kwargs)

        env.reset = counted

    def start_correction(self, step: int) -> None:
        return None

    @torch.no_grad()
    def act_batch(self, groups):
        self.k += 1
        t = self.student._tensors(groups, batched=True)
        if self.k > self.steps:
            return self.student.net(t).numpy()
        return self.student.net.mean(t, self.student.net.extractor.z(t) + self.shift).clamp(-1.0, 1.0).numpy()


def test_evaluation_acts_with_the_shift_over_the_first_steps_only(cautious):
    perturb = next(c.perturb for c in get_suite("perturbations", ("friction_0.25",), DEFAULT_HAND))
    cfg = EnvConfig(hand=DEFAULT_HAND, randomization=default_randomization(DEFAULT_HAND), perturb=perturb,
                    episode_steps=3 * STEPS)
    runs = {}
    for name in ("cautious", "reference", "student"):
        env = RotateCupVec(cfg, num_envs=2, seed=7, nthread=1)
        policy = {"cautious": cautious, "student": load_bundle("student"),
                  "reference": Reference(env, load_bundle("student"), cautious.config.start_shift, STEPS)}[name]
        runs[name] = [dataclasses.astuple(e) for e in run_episodes(policy, env, 3, seed=7)]
        env.close()
    assert runs["cautious"] == runs["reference"]  # every metric of every episode, the second chunk's too
    assert runs["cautious"] != runs["student"]  # and the shift changed how it acted


@pytest.mark.parametrize(("changes", "message"), [
    ({"start_steps": 3, "start_shift": (0.1,)}, "one value per latent dimension"),
    ({"start_steps": 0, "start_shift": (0.0,) * 8}, "start_steps is 0"),
    ({"start_steps": 3, "start_shift": (float("nan"),) * 8}, "must be finite"),
    ({"start_steps": -1}, "start_steps must be >= 0"),
])
def test_a_bad_cautious_start_is_refused(changes, message):
    with pytest.raises(BundleError, match=message):
        dataclasses.replace(load_bundle("student").config, **changes)
