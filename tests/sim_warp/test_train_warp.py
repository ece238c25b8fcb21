"""GPU-recipe training on Warp's CPU device: a tiny teacher run writes a bundle that loads and evaluates like a
CPU-trained one, the student distills on the warp backend, and the command line starts from the GPU recipe."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from envs.config import EnvConfig
from envs.constants import DEFAULT_HAND
from envs.sim_identity import sim_record
from rotation import cli
from rotation.bundles import load_bundle
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig
from rotation.sim_warp.core import physics_problem
from rotation.train import teacher
from rotation.train.teacher_config import GPU_RECIPE

HAND = "digit360"
"""The hand these runs train on: the warp backend does not simulate the digit360_v4 hand's physics yet."""


def _bundle(path, source: str = "privileged"):
    """A bundle trained on HAND (as the shipped ones were before digit360_v4), with the normalization statistics of
    a trained one."""
    torch.manual_seed(0)
    bundle = PolicyBundle(BundleConfig(latent_source=source, sim=sim_record(EnvConfig(hand=HAND))))  # type: ignore[arg-type]
    norm = bundle.net.extractor.proprio_norm
    with torch.no_grad():
        norm.mean.normal_()
        norm.var.uniform_(0.5, 1.5)
        norm.count.fill_(1000.0)
    return bundle.save(path)


def test_the_command_line_starts_from_the_gpu_recipe():
    parser = cli.build_parser(only="train-teacher")
    args = parser.parse_args(["train-teacher", "--backend", "warp", "--device", "cpu", "--n-epochs", "2", "--hand",
                              HAND])
    cfg = teacher.config_from_args(args)
    assert (cfg.num_envs, cfg.n_steps, cfg.learning_rate) == (GPU_RECIPE["num_envs"], GPU_RECIPE["n_steps"],
                                                              GPU_RECIPE["learning_rate"])
    assert cfg.n_epochs == 2 and cfg.device == "cpu"  # given options win
    assert cfg.batch_size == cfg.num_envs * cfg.n_steps // 4
    cpu = teacher.config_from_args(parser.parse_args(["train-teacher"]))
    assert cpu == teacher.Config()  # the cpu backend keeps its own defaults


def test_a_hand_the_warp_backend_does_not_simulate_is_refused_in_one_line(tmp_path, capsys):
    """The digit360_v4 hand's physics run on the cpu backend only: a warp run on it is refused before it starts, in
    one line that names the hand to pass (as is the default hand, when it is that one)."""
    parser = cli.build_parser(only="train-teacher")
    for hand in {"digit360_v4", DEFAULT_HAND}:
        if physics_problem(EnvConfig(hand=hand)) is None:
            continue
        argv = ["train-teacher", "--backend", "warp", "--device", "cpu", "--out", str(tmp_path / "t")]
        if hand != DEFAULT_HAND:
            argv += ["--hand", hand]
        with pytest.raises(ValueError, match=f"backend: the {hand} hand's physics .* pass --hand {HAND} to train on "
                                             "the warp backend"):
            teacher.config_from_args(parser.parse_args(argv))
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"--hand {HAND}" in err and "Traceback" not in err, err
    assert not (tmp_path / "t").exists()


def test_tiny_teacher_run_writes_a_bundle_that_evaluates(tmp_path, capsys):
    bundle = teacher.run(_warp_cfg(tmp_path))
    loaded = load_bundle(tmp_path / "teacher" / "bundle")
    assert loaded.config.latent_source == "privileged" and loaded.config.card["backend"] == "warp"
    obs = {"proprio": np.zeros((3, 32), np.float32), "priv": np.zeros(9, np.float32)}
    assert np.allclose(loaded.act(obs), bundle.act(obs))
    rows = [json.loads(line) for line in (tmp_path / "teacher" / "curves.jsonl").read_text().splitlines()]
    assert rows and rows[-1]["steps"] == 32
    assert any((tmp_path / "teacher" / "tb").rglob("events.out.tfevents.*"))
    status = cli.main(["evaluate", "--backend", "warp", "--warp-device", "cpu", "--policy",
                       f"t={tmp_path / 'teacher' / 'bundle'}", "--episodes", "2", "--num-envs", "2",
                       "--episode-steps", "4", "--out", str(tmp_path / "eval"), "--no-progress"])
    assert status == 0, capsys.readouterr().err
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert results["rows"][0]["policy"] == "t"
    status = cli.main(["evaluate", "--policy", f"t={tmp_path / 'teacher' / 'bundle'}", "--episodes", "2",
                       "--num-envs", "2", "--episode-steps", "4", "--out", str(tmp_path / "eval_cpu"),
                       "--no-progress"])  # and on the cpu backend, like a teacher trained there
    assert status == 0, capsys.readouterr().err

    from rotation.train import student

    scfg = student.Config(teacher=str(tmp_path / "teacher" / "bundle"), out=tmp_path / "student", backend="warp",
                          num_envs=2, total_steps=8, checkpoint_every=8, log_every=2, progress=False)
    result = student.run(scfg)
    assert load_bundle(result.bundle_dir).config.latent_source == "adaptation"


def _warp_cfg(tmp_path, **kw) -> teacher.Config:
    base = dict(backend="warp", hand=HAND, device="cpu", num_envs=4, n_steps=4, batch_size=8, n_epochs=2,
                total_steps=32, checkpoint_every=16, out=tmp_path / "teacher", progress=False,
                episode_steps=4)  # every env ends an episode each iteration: a curve row each time
    return teacher.Config(**{**base, **kw})


def test_warp_teacher_resumes_with_its_step_count(tmp_path):
    teacher.run(_warp_cfg(tmp_path))
    last = tmp_path / "teacher" / "checkpoints" / "last.pt"
    with pytest.raises(ValueError, match="holds"):  # the run is not overwritten without --resume
        teacher.run(_warp_cfg(tmp_path, total_steps=64))
    with pytest.raises(ValueError, match="n_epochs"):  # nor continued with other PPO options
        teacher.run(_warp_cfg(tmp_path, total_steps=64, n_epochs=3, resume=last))
    bundle = teacher.run(_warp_cfg(tmp_path, total_steps=64, resume=last))
    assert bundle.config.card["steps"] == 64 and bundle.config.card["resumed_from"] == str(last)
    rows = [json.loads(line) for line in (tmp_path / "teacher" / "curves.jsonl").read_text().splitlines()]
    assert [r["steps"] for r in rows] == sorted(r["steps"] for r in rows) and rows[-1]["steps"] == 64
    with pytest.raises(ValueError, match="cpu-backend checkpoint"):
        _warp_cfg(tmp_path, resume=tmp_path / "last.zip")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot be read"):
        teacher.run(_warp_cfg(tmp_path, out=tmp_path / "other", resume=tmp_path / "junk.pt"))


def test_warp_teacher_starts_from_a_bundle_with_a_critic_warmup(tmp_path):
    """--init-from copies a teacher bundle (here one made on the cpu, of HAND) into the actor; during the critic
    warm-up the actor, its log std and its normalization stay exactly as they were."""
    start_dir = _bundle(tmp_path / "start")
    start = load_bundle(start_dir)
    bundle = teacher.run(_warp_cfg(tmp_path, init_from=start_dir, critic_warmup=100))
    assert bundle.config.card["init_from"]
    for (name, a), b in zip(start.net.state_dict().items(), bundle.net.state_dict().values(), strict=True):
        assert torch.equal(a, b), name
    with pytest.raises(ValueError, match="not a teacher bundle"):
        teacher.run(_warp_cfg(tmp_path, out=tmp_path / "s", init_from=_bundle(tmp_path / "student", "adaptation")))


@pytest.mark.gpu
def test_tiny_teacher_run_on_the_gpu(tmp_path):
    cfg = teacher.Config(backend="warp", hand=HAND, device="cuda", num_envs=256, n_steps=8, batch_size=512, n_epochs=2,
                         total_steps=256 * 8 * 2, out=tmp_path / "teacher", progress=False)
    teacher.run(cfg)
    assert load_bundle(tmp_path / "teacher" / "bundle").config.card["backend"] == "warp"


def test_student_rollout_on_warp_stays_on_the_device(tmp_path):
    """The warp student's rollout hands the networks device tensors and sums episodes on the device; its episode
    means match the cpu backend's on the same seed (4-step episodes of a held grasp, zero actions)."""
    from rotation.train import student

    keys = {"proprio", "proprio_hist", "priv"}
    means = {}
    start = str(_bundle(tmp_path / "teacher"))
    for backend, cls in (("warp", student.DeviceRollout), ("cpu", student.HostRollout)):
        cfg = student.Config(teacher=start, out=tmp_path / backend, backend=backend, device="cpu", num_envs=2,
                             env=EnvConfig(hand=HAND, episode_steps=4), progress=False)
        roll = cls(cfg, keys)
        try:
            obs = roll.reset(seed=3)
            assert all(isinstance(v, torch.Tensor) and v.shape[0] == 2 for v in obs.values())
            assert roll.collect() == {}
            for _ in range(4):
                obs = roll.step(torch.zeros(2, 16))
            means[backend] = roll.collect()
        finally:
            roll.close()
    assert means["warp"]["ep_length"] == means["cpu"]["ep_length"] == 4.0
    assert means["warp"]["ttf"] == means["cpu"]["ttf"] == 1.0
    # float32 physics: a grasp that tips the cup (world 0 here) drifts apart fastest (-1.26 vs -1.15 measured)
    assert means["warp"]["ep_reward"] == pytest.approx(means["cpu"]["ep_reward"], abs=0.25)
