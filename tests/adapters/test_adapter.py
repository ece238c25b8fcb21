"""The tactile adapter: exactly the student at initialization, gradients only into the adapter, a tiny fine-tuning
run that reduces the latent error, bundle round trip and mismatch errors, evaluation with touch."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from adapters.bundle import TouchUnavailable, build_adapted, load_adapter
from adapters.finetune import core
from adapters.finetune import job as finetune
from adapters.model import TRACKING_DIM, AdapterNetConfig, TouchAdapter
from envs.config import EnvConfig
from envs.constants import PRIV_FIELDS
from envs.core import RotateCupVec
from rotation.bundles import load_bundle
from rotation.evaluate import job
from rotation.evaluate.rollout import run_episodes
from rotation.policy.bundle_config import BundleError

ENCODER = "sparshx-tinier-sim"


def _windows(policy, obs):
    return {f: {w: obs["tactile"][f][w] for w in policy.windows} for f in policy.fingers}


def test_zero_init_acts_exactly_like_the_student(env_obs):
    env, obs = env_obs
    policy = build_adapted("student", ENCODER, ("img", "pressure"), seed=3)
    groups = {k: obs[k] for k in policy.config.obs_groups}
    corr = policy.correction(_windows(policy, obs), groups)
    assert corr.shape == (2, policy.config.latent_dim) and np.all(corr == 0.0)
    student = load_bundle("student")
    assert np.array_equal(policy.act_batch(groups, correction=corr), student.act_batch(groups))
    assert np.array_equal(policy.act_batch(groups), student.act_batch(groups))
    one = {k: v[0] for k, v in groups.items()}
    assert np.array_equal(policy.act(one, correction=corr[0]), student.act(one))


def test_the_traced_paths_give_the_eager_corrections_and_actions_bit_for_bit(env_obs):
    """Deploy traces the student's acting paths and the encoder (AdaptedPolicy.prepare_realtime): same numbers, and
    non-finite windows are still refused."""
    env, obs = env_obs
    policy = build_adapted("student", ENCODER, ("img", "imu", "pressure"), seed=3)
    torch.nn.init.normal_(policy.adapter.zero.weight, std=0.05)  # a non-zero correction
    groups = {k: obs[k] for k in policy.config.obs_groups}
    windows = _windows(policy, obs)
    eager_corr = policy.correction(windows, groups)
    one = {k: v[0] for k, v in groups.items()}
    eager_act = policy.act(one, correction=eager_corr[0])
    eager_student = policy.act(one)
    assert np.abs(eager_corr).max() > 0
    policy.prepare_realtime()
    for _ in range(2):
        assert np.array_equal(policy.correction(windows, groups), eager_corr)
        assert np.array_equal(policy.act(one, correction=eager_corr[0]), eager_act)
        assert np.array_equal(policy.act(one), eager_student)
    assert len(policy.traced_encoders) == 1
    bad = {f: dict(w) for f, w in windows.items()}
    bad["index"]["imu"] = np.full_like(bad["index"]["imu"], np.nan)
    with pytest.raises(TouchUnavailable, match="non-finite"):
        policy.correction(bad, groups)


def test_gradients_reach_only_the_adapter(env_obs):
    env, obs = env_obs
    policy = build_adapted("student", ENCODER, ("img",), seed=0)
    groups = {k: obs[k] for k in policy.config.obs_groups}
    tokens = policy.tokens(_windows(policy, obs))
    z = policy.student_latent(groups)
    loss = (z + policy.adapter(tokens, z) - 1.0).pow(2).mean()
    loss.backward()
    grads = {n for n, p in policy.adapter.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert "zero.weight" in grads and "zero.bias" in grads  # the zero layer learns first (the rest sees 0 gradient)
    for module in (policy.encoder, policy.student.net):
        assert all(not p.requires_grad and p.grad is None for p in module.parameters())
    assert not tokens["index"]["img"].requires_grad


def test_the_action_matching_term_is_the_frozen_actors_error_and_trains_only_the_adapter(env_obs):
    env, obs = env_obs
    policy = build_adapted("student", ENCODER, ("pressure",), seed=0)
    teacher = load_bundle("teacher")
    groups = {k: obs[k] for k in policy.config.obs_groups}
    with torch.no_grad():
        z_teacher = teacher.net.extractor.z(teacher._tensors({k: obs[k] for k in teacher.config.obs_groups}, True))
    buf = core.TokenBuffer(4, policy.adapter.cfg.samples, policy.adapter.interface.counts,
                               policy.adapter.interface.width, policy.adapter.cfg.latent_dim, policy.proprio_dim)
    buf.add(policy.tokens(_windows(policy, obs)), policy.student_latent(groups), z_teacher,
            policy.proprio_features(groups))
    batch = buf.batch(torch.arange(2))
    head = policy.student.net.head
    # the head on the student's own latent is the student's action mean
    assert torch.allclose(head(batch.proprio, batch.z_student).clamp(-1, 1),
                          torch.as_tensor(policy.student.act_batch(groups)), atol=1e-6)
    student_err = core.errors_to_teacher(head, batch.proprio, batch.z_student, batch.z_student,
                                             batch.z_teacher)["action_mse"]
    assert student_err > 0
    latent = float(((batch.z_student - batch.z_teacher) ** 2).mean())
    optim = torch.optim.SGD(policy.adapter.parameters(), lr=0.0)  # lr 0: the returned loss at the zero adapter
    assert core.adam_step(policy.adapter, optim, batch, head, 0.0) == pytest.approx(latent, rel=1e-6)
    assert core.adam_step(policy.adapter, optim, batch, head, 10.0) == pytest.approx(latent + 10 * student_err,
                                                                                        rel=1e-5)
    assert all(p.grad is None for p in policy.student.net.parameters())
    optim = torch.optim.Adam(policy.adapter.parameters(), lr=1e-3)
    for _ in range(150):
        core.adam_step(policy.adapter, optim, batch, head, 10.0)
    with torch.no_grad():
        z = batch.z_student + policy.adapter(batch.tokens, batch.z_student)
    errors = core.errors_to_teacher(head, batch.proprio, z, batch.z_student, batch.z_teacher)
    assert errors["action_mse"] < 0.1 * student_err and errors["student_action_mse"] == pytest.approx(student_err)
    assert all(p.grad is None for p in policy.student.net.parameters())


def test_missing_or_bad_touch_is_touch_unavailable(env_obs):
    env, obs = env_obs
    policy = build_adapted("student", ENCODER, ("img", "pressure"))
    groups = {k: obs[k] for k in policy.config.obs_groups}
    windows = _windows(policy, obs)
    with pytest.raises(TouchUnavailable, match="thumb"):
        policy.correction({f: w for f, w in windows.items() if f != "thumb"}, groups)
    with pytest.raises(TouchUnavailable, match="pressure"):
        policy.correction({f: {"image": w["image"]} for f, w in windows.items()}, groups)
    bad = {f: dict(w) for f, w in windows.items()}
    bad["ring"]["pressure"] = np.full_like(bad["ring"]["pressure"], np.nan)
    with pytest.raises(TouchUnavailable, match="non-finite"):
        policy.correction(bad, groups)


def test_a_blind_adapter_reads_the_latent_and_the_tracking_but_not_the_touch():
    """The ablation without touch (--blind-touch): other tokens give the same correction, another latent or joint
    tracking another one; the same network reading touch tells the tokens apart."""
    torch.manual_seed(0)
    nets = {}
    for touch in (True, False):
        cfg = AdapterNetConfig(samples=("index", "thumb"), groups=(("img", 4),), width=8, latent_dim=3, hidden=(16,),
                               tracking=True, touch=touch)
        nets[touch] = net = TouchAdapter(cfg)
        torch.nn.init.normal_(net.zero.weight)  # trained: no longer the zero map
    tokens = [{s: {"img": torch.randn(2, 4, 8)} for s in ("index", "thumb")} for _ in range(2)]
    z, track = torch.randn(2, 3), torch.randn(2, TRACKING_DIM)
    blind, sighted = nets[False], nets[True]
    assert torch.equal(blind(tokens[0], z, track), blind(tokens[1], z, track))
    assert not torch.allclose(blind(tokens[0], z, track), blind(tokens[0], z, track + 1.0))
    assert not torch.allclose(blind(tokens[0], z, track), blind(tokens[0], z + 1.0, track))
    assert not torch.allclose(sighted(tokens[0], z, track), sighted(tokens[1], z, track))
    assert finetune.Config(out=Path("x"), blind_touch=True, tracking=True).blind_touch


def test_the_training_randomization_is_the_hands_own_reaching_slippery_and_heavy_cups():
    """The adapter trains on its student's hand's physics (cups, friction split, hardware randomization), widened to
    the perturbation suite's slippery and heavy extremes; the first hand model keeps its own widened ranges."""
    from adapters.finetune.config import hard_randomization
    from envs.physics import MAX_OBJECT_MASS, default_randomization

    cfg = finetune.Config(out=Path("x"))
    rc, hand = cfg.env.randomization, default_randomization(cfg.env.hand)
    assert cfg.env.hand == "digit360_v4" and cfg.env.tactile
    kept = ("scales", "friction", "friction_log", "link_friction", "joint_friction", "torque_scale", "action_delay",
            "impratio", "contact_timeconst", "noslip_dropout")
    assert {k: getattr(rc, k) for k in kept} == {k: getattr(hand, k) for k in kept}
    assert rc.surface_friction == (0.25, 1.0)  # the suite's friction x0.25 at its low end
    assert rc.mass == (hand.mass[0], MAX_OBJECT_MASS) and hand.mass[1] + 0.1 <= rc.mass[1]  # and its +0.1 kg
    first = hard_randomization("digit360")
    assert (first.friction, first.mass, first.link_friction) == ((0.075, 1.5), (0.05, 0.45), None)
    skin = finetune.Config(out=Path("x"), modalities="skin", encoder="skin_encoder")
    assert skin.env.hand == "xela" and skin.env.randomization == hard_randomization("xela")


def test_adapter_network_checks_its_inputs():
    with pytest.raises(ValueError, match="samples"):
        AdapterNetConfig(samples=(), groups=(("img", 196),), width=96)
    with pytest.raises(ValueError, match="multiple"):
        AdapterNetConfig(samples=("index",), groups=(("img", 196),), width=90, pool_heads=4)
    net = TouchAdapter(AdapterNetConfig(samples=("index", "thumb"), groups=(("img", 4),), width=8, latent_dim=3,
                                        hidden=(16,)))
    with pytest.raises(ValueError, match="thumb"):
        net({"index": {"img": torch.zeros(2, 4, 8)}}, torch.zeros(2, 3))
    assert torch.equal(net({s: {"img": torch.randn(2, 4, 8)} for s in ("index", "thumb")}, torch.zeros(2, 3)),
                       torch.zeros(2, 3))


def _tiny_cfg(out, **kw) -> finetune.Config:
    base = dict(out=out, modalities="pressure", total_steps=256, num_envs=2, touch_every=2, student_steps=64,
                updates=16, batch_size=32, buffer_size=512, lr=1e-3, checkpoint_every=128, log_every=8,
                progress=False, torch_threads=1, nthread=1, seed=0)
    return finetune.Config(**{**base, **kw})


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("adapter") / "run"
    return out, finetune.run(_tiny_cfg(out))


@pytest.fixture(scope="module")
def learning_run(tmp_path_factory):
    """A run long and wide enough to judge learning by: 8 envs of 128 steps (2 envs of 128 steps swung the adapted
    to student error ratio between 0.3 and 3 from one refresh to the next on the vendor-kinematics pair, whose
    student's own error jumps from 0.02 to 0.19 with a new episode); about 0.65 at the end on two seeds."""
    out = tmp_path_factory.mktemp("adapter_learning") / "run"
    return out, finetune.run(_tiny_cfg(out, num_envs=8, total_steps=1024, student_steps=256, checkpoint_every=512,
                                       log_every=16))


def test_tiny_finetuning_reduces_the_latent_error(learning_run):
    out, result = learning_run
    hist = result.history
    assert len(hist) >= 4
    # the error of the adapted latent, measured on each refresh's fresh samples before training on them, against
    # the student's own error on the same samples: the adapter must take a clear share of it away
    late = hist[len(hist) // 2:]
    adapted = np.mean([h["latent_mse"] for h in late])
    student = np.mean([h["student_mse"] for h in late])
    assert adapted < 0.8 * student, (adapted, student)
    assert all(h["action_mse"] >= 0 and h["student_action_mse"] > 0 for h in hist)  # logged beside the latent's
    rows = [json.loads(line) for line in (out / "curves.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in rows] == [h["env_steps"] for h in hist]


def test_bundle_round_trip_and_as_a_policy(tiny_run):
    out, result = tiny_run
    policy = load_adapter(result.bundle_dir)
    assert policy.adapter_config.modalities == ("pressure",) and policy.touch_every == 2
    assert policy.adapter_config.card["trained_by"] == "rotate finetune-adapter"
    assert policy.adapter_config.card["touch_delay"].startswith("touch delay 'measured': ")  # trained with it
    assert any(p.abs().sum() > 0 for p in policy.adapter.zero.parameters())  # trained: no longer the zero map
    same = load_bundle(result.bundle_dir)  # `--policy NAME=PATH` takes an adapter bundle
    assert type(same).__name__ == "AdaptedPolicy" and same.config.touch_encoder == ENCODER


def test_finetune_resume_is_exact(tiny_run, tmp_path):
    out, result = tiny_run
    part = tmp_path / "part"
    finetune.run(_tiny_cfg(part, total_steps=128))
    resumed = finetune.run(_tiny_cfg(part, total_steps=256, resume=True))
    a, b = load_adapter(result.bundle_dir), load_adapter(resumed.bundle_dir)
    for (name, x), y in zip(a.adapter.state_dict().items(), b.adapter.state_dict().values(), strict=True):
        assert torch.equal(x, y), name


def test_mismatched_student_or_encoder_is_refused(tiny_run, tmp_path):
    out, result = tiny_run
    student = tmp_path / "student"
    shutil.copytree(_shipped("student"), student)
    policy = build_adapted(str(student), ENCODER, ("img",))
    policy.save(tmp_path / "adapter")
    assert load_adapter(tmp_path / "adapter").config.adapter == str(tmp_path / "adapter")
    weights = student / "model.safetensors"
    data = bytearray(weights.read_bytes())
    original = bytes(data)
    data[-1] ^= 1  # another student (one weight bit differs)
    weights.write_bytes(bytes(data))
    with pytest.raises(BundleError, match="retrain the adapter for this student"):
        load_adapter(tmp_path / "adapter")
    weights.write_bytes(original)
    cfg = json.loads((tmp_path / "adapter" / "config.json").read_text())
    cfg["encoder"] = str(tmp_path / "nowhere.safetensors")
    (tmp_path / "adapter" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(BundleError, match="encoder"):
        load_adapter(tmp_path / "adapter")


def test_init_from_carries_an_adapter_to_another_student(tiny_run, tmp_path):
    """--init-from starts from a trained adapter's weights, also for a student other than the one it named (a
    student fine-tuned by finetune-student keeps its phi); another network or modality set is refused."""
    out, result = tiny_run
    student = tmp_path / "student"
    shutil.copytree(_shipped("student"), student)
    weights = student / "model.safetensors"
    data = bytearray(weights.read_bytes())
    data[-1] ^= 1  # another student
    weights.write_bytes(bytes(data))
    job = core.Job.start_from(_tiny_cfg(tmp_path / "carried", student=str(student),
                                            init_from=str(result.bundle_dir)))
    trained = load_adapter(result.bundle_dir).adapter.state_dict()
    for name, value in job.policy.adapter.state_dict().items():
        assert torch.equal(value, trained[name]), name
    with pytest.raises(ValueError, match="init_from: .*modalities"):
        core.Job.start_from(_tiny_cfg(tmp_path / "other", modalities="imu", init_from=str(result.bundle_dir)))
    with pytest.raises(ValueError, match="init_from: .*not an adapter bundle"):
        core.Job.start_from(_tiny_cfg(tmp_path / "none", init_from=str(tmp_path)))


def test_anchor_holds_light_cups_at_its_correction_and_heavy_ones_at_the_teachers_z(tiny_run, env_obs, tmp_path):
    """--anchor: a frozen copy of another adapter whose correction is the target on cups lighter than anchor_mass;
    the teacher's z stays the target on heavier ones, and everywhere without an anchor."""
    from adapters.finetune.sim import anchored_target

    out, result = tiny_run
    job = core.Job.start_from(_tiny_cfg(tmp_path / "anchored", anchor=str(result.bundle_dir), anchor_mass=0.2))
    trained = load_adapter(result.bundle_dir).adapter.state_dict()
    for name, value in job.anchor.state_dict().items():
        assert torch.equal(value, trained[name]), name
    assert not any(p.requires_grad for p in job.anchor.parameters())  # frozen, and not what the optimizer steps
    stepped = {id(p) for g in job.optim.param_groups for p in g["params"]}
    assert stepped.isdisjoint(id(p) for p in job.anchor.parameters())
    assert all(p.abs().sum() == 0 for p in job.policy.adapter.zero.parameters())  # the adapter itself starts at zero
    _, obs = env_obs
    policy = job.policy
    tokens = policy.tokens(policy.env_windows(obs))
    groups = {k: obs[k] for k in policy.config.obs_groups}
    with torch.no_grad():
        z_student = policy.student_latent(groups)
        held = z_student + job.anchor(tokens, z_student)
    assert not torch.allclose(held, z_student)  # the trained anchor corrects
    z_teacher = torch.randn_like(z_student)
    priv = np.array(obs["priv"], copy=True)
    priv[:, PRIV_FIELDS.index("mass")] = [0.1, 0.3]
    target = anchored_target(job, priv, tokens, z_student, z_teacher)
    assert torch.equal(target[0], held[0]) and torch.equal(target[1], z_teacher[1])
    job.anchor = None
    assert torch.equal(anchored_target(job, priv, tokens, z_student, z_teacher), z_teacher)
    with pytest.raises(ValueError, match="anchor: .*modalities"):
        core.Job.start_from(_tiny_cfg(tmp_path / "other", modalities="imu", anchor=str(result.bundle_dir)))
    with pytest.raises(ValueError, match="leave --anchor out with --sessions"):
        _tiny_cfg(tmp_path / "s", sessions=(tmp_path,), modalities="imu", anchor=str(result.bundle_dir))


def _shipped(name):
    from rotation.policy.bundle import resolve_bundle

    return resolve_bundle(name)


def test_evaluate_with_an_adapter(tiny_run, tmp_path):
    out, result = tiny_run
    cfg = job.Config(policies={"student": "student", "adapter": str(result.bundle_dir)}, episodes=2, episode_steps=8,
                     out=tmp_path / "eval", num_envs=2, nthread=1, progress=False, seed=100)
    rows = job.run(cfg)
    assert [r["policy"] for r in rows] == ["student", "adapter"]
    # the touch sensors change nothing for a policy that does not read them: the same student episodes
    plain = job.run(job.Config(policies={"student": "student"}, episodes=2, episode_steps=8, out=tmp_path / "plain",
                               num_envs=2, nthread=1, progress=False, seed=100))
    assert {k: v for k, v in plain[0].items()} == {k: v for k, v in rows[0].items()}
    with pytest.raises(ValueError, match="cpu"):
        job.run(job.Config(policies={"adapter": str(result.bundle_dir)}, backend="warp", episodes=1,
                           out=tmp_path / "w", progress=False))


def test_rollout_refuses_touch_policy_without_touch(tiny_run):
    out, result = tiny_run
    env = RotateCupVec(EnvConfig(episode_steps=4), num_envs=1, seed=0, nthread=1)
    try:
        with pytest.raises(ValueError, match="tactile"):
            run_episodes(load_adapter(result.bundle_dir), env, 1, 0)
    finally:
        env.close()


def test_a_checkpoint_another_run_wrote_is_refused_and_left_alone(tiny_run, tmp_path):
    """`--resume` adopts the newest ckpt_*.pt in --out only if it carries this run's id (run.json): another run's
    checkpoint copied in is refused in one line and nothing changes."""
    from envs.errors import RequestRefused

    mine, other = tmp_path / "mine", tmp_path / "other"
    shutil.copytree(tiny_run[0], mine)  # a finished run of its own (the module's)
    finetune.run(_tiny_cfg(other, total_steps=128, seed=4))
    assert (mine / "run.json").is_file()
    foreign = sorted(other.glob("ckpt_*.pt"))[-1]
    shutil.copy(foreign, mine / "ckpt_999999999.pt")  # the newest name in mine
    before = {p: p.read_bytes() for p in mine.rglob("*") if p.is_file()}
    with pytest.raises(RequestRefused, match="is not a checkpoint this run wrote"):
        finetune.run(_tiny_cfg(mine, total_steps=512, resume=True))
    assert {p: p.read_bytes() for p in mine.rglob("*") if p.is_file()} == before
