"""Policy bundle: round trip, SB3 import, teacher -> student, ONNX parity, and every kind of bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from gymnasium import spaces
from safetensors.torch import load_file, save_file

from rotation.bundles import load_bundle
from rotation.policy import bundle as B
from rotation.policy.bundle import PolicyBundle
from rotation.policy.bundle_config import BundleConfig, BundleError
from rotation.policy.export import export_onnx
from rotation.policy.features import policy_kwargs
from rotation.policy.networks import EnvFactorEncoderConfig


def random_obs(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "proprio": rng.normal(size=(n, 3, 32)).astype(np.float32),
        "proprio_hist": rng.normal(size=(n, 30, 32)).astype(np.float32),
        "priv": rng.uniform(0, 1, size=(n, 9)).astype(np.float32),
    }


def randomized(bundle: PolicyBundle, seed: int = 0) -> PolicyBundle:
    """Give every tensor (normalization statistics included) non-trivial values, so round trips are meaningful."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, t in bundle.net.state_dict().items():
            if name.endswith("var"):
                t.copy_(torch.rand(t.shape, generator=g) + 0.5)
            elif name.endswith("count"):
                t.fill_(1000)
            elif t.dim() >= 2:  # weights at a fan-in scale: activations stay O(1), as in a trained network
                t.copy_(torch.randn(t.shape, generator=g) * (1.0 / t[0].numel()) ** 0.5)
            else:
                t.copy_(torch.randn(t.shape, generator=g) * 0.3)
    return bundle


@pytest.fixture
def teacher() -> PolicyBundle:
    return randomized(PolicyBundle(BundleConfig(card={"note": "random init"})))


def test_round_trip(tmp_path, teacher):
    path = teacher.save(tmp_path / "teacher")
    assert sorted(p.name for p in path.iterdir()) == ["config.json", "model.safetensors"]
    cfg = json.loads((path / "config.json").read_text())
    assert cfg["env_version"] == "RotateCup-v0" and cfg["format_version"] == B.FORMAT_VERSION
    assert cfg["obs_groups"] == {"proprio": [3, 32], "priv": [9]}
    assert "extractor.proprio_norm.mean" in load_file(path / "model.safetensors")

    loaded = load_bundle(path)
    assert loaded.config == teacher.config
    obs = random_obs(7)
    a = loaded.act_batch(obs)
    assert a.shape == (7, 16) and a.dtype == np.float32
    np.testing.assert_array_equal(a, teacher.act_batch(obs))
    assert np.all(np.abs(a) <= 1.0)
    single = {k: v[3] for k, v in obs.items()}
    np.testing.assert_allclose(loaded.act(single), a[3], atol=1e-6)
    assert loaded.latent(obs).shape == (7, 8) and loaded.latent(single).shape == (8,)


def test_from_sb3_matches_sb3_policy():
    from stable_baselines3.common.policies import MultiInputActorCriticPolicy

    space = spaces.Dict({k: spaces.Box(-np.inf, np.inf, v.shape[1:], np.float32) for k, v in random_obs(1).items()})
    policy = MultiInputActorCriticPolicy(space, spaces.Box(-1, 1, (16,), np.float32), lambda _: 3e-4,
                                         **policy_kwargs(EnvFactorEncoderConfig(hidden=(64, 32))))
    obs = random_obs(5)
    policy.set_training_mode(True)
    policy.extract_features({k: torch.as_tensor(v) for k, v in obs.items()})  # move the normalization statistics
    policy.set_training_mode(False)
    bundle = PolicyBundle.from_sb3(policy, card={"steps": 0})
    assert bundle.config.encoder == EnvFactorEncoderConfig(hidden=(64, 32))
    assert bundle.config.actor_hidden == (512, 256, 128)
    expected, _ = policy.predict(obs, deterministic=True)  # SB3 clips to the action space
    np.testing.assert_allclose(bundle.act_batch(obs), expected, atol=1e-6)


def test_to_student_shares_actor(teacher):
    student = teacher.to_student()
    assert student.config.latent_source == "adaptation"
    assert student.config.obs_groups == {"proprio": (3, 32), "proprio_hist": (30, 32)}
    obs = {k: torch.as_tensor(v) for k, v in random_obs(4).items()}
    z = teacher.net.extractor.z(obs)
    torch.testing.assert_close(student.net.mean(obs, z), teacher.net.mean(obs))  # same actor given the same z
    with pytest.raises(BundleError, match="teacher"):
        student.to_student()


def test_with_teacher_latent_is_the_students_actor_on_the_teachers_z(tmp_path, teacher):
    student = randomized(teacher.to_student(), seed=1)  # its own actor and normalization, as after fine-tuning
    oracle = student.with_teacher_latent(teacher, card={"role": "oracle-latent student"})
    assert oracle.config.latent_source == "privileged" and oracle.config.obs_groups == teacher.config.obs_groups
    obs = {k: torch.as_tensor(v) for k, v in random_obs(5, seed=3).items()}
    z = teacher.net.extractor.z(obs)
    torch.testing.assert_close(oracle.net.mean(obs), student.net.mean(obs, z))
    assert not torch.allclose(oracle.net.mean(obs), teacher.net.mean(obs))
    loaded = load_bundle(oracle.save(tmp_path / "oracle"))  # an ordinary teacher-kind bundle for evaluate
    np.testing.assert_array_equal(loaded.act_batch(random_obs(5, seed=3)), oracle.act_batch(random_obs(5, seed=3)))
    with pytest.raises(BundleError, match="student bundle"):
        teacher.with_teacher_latent(teacher)
    with pytest.raises(BundleError, match="teacher bundle"):
        student.with_teacher_latent(student)


@pytest.mark.parametrize("kind", ["teacher", "student"])
def test_onnx_matches_torch(tmp_path, teacher, kind):
    import onnxruntime as ort

    bundle = teacher if kind == "teacher" else randomized(teacher.to_student(), seed=1)
    path = export_onnx(bundle, tmp_path / f"{kind}.onnx")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == list(bundle.config.obs_groups)
    obs = random_obs(6, seed=2)
    feeds = {k: obs[k] for k in bundle.config.obs_groups}
    action, latent = sess.run(["action", "latent"], feeds)
    np.testing.assert_allclose(action, bundle.act_batch(obs), atol=1e-5, rtol=0)
    np.testing.assert_allclose(latent, bundle.latent(obs), atol=1e-5, rtol=0)


# ---------------------------------------------------------------------------------------------------- bad input


def edit_config(path, **changes):
    cfg = json.loads((path / "config.json").read_text())
    cfg.update(changes)
    (path / "config.json").write_text(json.dumps(cfg))


def test_rejects_other_env_and_format_versions(tmp_path, teacher):
    path = teacher.save(tmp_path / "b")
    edit_config(path, env_version="RotateCube-v3")
    with pytest.raises(BundleError, match=r"'RotateCube-v3', expected 'RotateCup-v0'"):
        load_bundle(path)
    edit_config(path, env_version="RotateCup-v0", format_version=99)
    with pytest.raises(BundleError, match=r"format version 99.*reads format version 1"):
        load_bundle(path)


def test_rejects_missing_files(tmp_path, teacher):
    path = teacher.save(tmp_path / "b")
    (path / "model.safetensors").unlink()
    with pytest.raises(BundleError, match="missing model.safetensors"):
        load_bundle(path)
    (path / "config.json").unlink()
    with pytest.raises(BundleError, match="missing config.json"):
        load_bundle(path)


def test_unknown_name_lists_shipped(monkeypatch, tmp_path, teacher):
    monkeypatch.setattr(B, "SHIPPED_DIR", tmp_path)
    with pytest.raises(BundleError, match="none are shipped"):
        load_bundle("teacher")
    teacher.save(tmp_path / "teacher")
    assert load_bundle("teacher").config == teacher.config  # a name resolves to the shipped directory
    with pytest.raises(BundleError, match="shipped bundles: teacher"):
        load_bundle("no_such_policy")


def test_rejects_mismatched_sizes(tmp_path, teacher):
    path = teacher.save(tmp_path / "b")
    cfg = json.loads((path / "config.json").read_text())
    cfg["encoder"]["hidden"] = [64, 32]
    (path / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(BundleError, match=r"extractor.encoder.mlp.0.weight.*shape \(256, 9\), expected \(64, 9\)"):
        load_bundle(path)
    edit_config(path, obs_groups={"proprio": [3, 32], "priv": [12]})
    with pytest.raises(BundleError, match="do not match the networks' inputs"):
        load_bundle(path)
    edit_config(path, mystery=1)
    with pytest.raises(BundleError, match="unknown config keys"):
        load_bundle(path)


def test_rejects_non_finite_weights(tmp_path, teacher):
    path = teacher.save(tmp_path / "b")
    tensors = load_file(path / "model.safetensors")
    tensors["actor.2.bias"][5] = float("nan")
    save_file(tensors, path / "model.safetensors")
    with pytest.raises(BundleError, match=r"non-finite.*actor\.2\.bias"):
        load_bundle(path)


def test_rejects_bad_observations(teacher):
    obs = {k: v[0] for k, v in random_obs(1).items()}
    with pytest.raises(BundleError, match=r"'priv' has shape \(7,\), expected \(9,\)"):
        teacher.act({**obs, "priv": np.zeros(7)})
    with pytest.raises(BundleError, match=r"missing group\(s\) \['priv'\]"):
        teacher.act({"proprio": obs["proprio"]})
    with pytest.raises(BundleError, match=r"expected \(N, 3, 32\)"):
        teacher.act_batch(obs)
    with pytest.raises(BundleError, match="non-finite"):
        teacher.act({**obs, "proprio": np.full((3, 32), np.nan)})
    with pytest.raises(BundleError, match="'proprio' contains non-finite"):  # float64 past float32's range
        teacher.act({**obs, "proprio": np.full((3, 32), 1e300)})
    with pytest.raises(BundleError, match="'priv' is not an array of numbers"):
        teacher.act({**obs, "priv": ["slippery"] * 9})


@pytest.mark.parametrize("shipped", ["teacher", "student"])
def test_the_traced_acting_path_gives_the_eager_actions_bit_for_bit(shipped):
    """Deploy acts with the network traced for one observation (PolicyBundle.prepare_realtime): same actions."""
    bundle = load_bundle(shipped)
    obs = random_obs(12, seed=3)
    singles = [{k: obs[k][i] for k in bundle.config.obs_groups} for i in range(12)]
    eager = [bundle.act(o) for o in singles]
    batch = {k: obs[k] for k in bundle.config.obs_groups}
    eager_batch = bundle.act_batch(batch)
    bundle.prepare_realtime()
    assert bundle.single is not None
    for _ in range(2):  # also after TorchScript's optimizing first calls
        assert all(np.array_equal(a, bundle.act(o)) for a, o in zip(eager, singles, strict=True))
    with pytest.raises(BundleError, match="non-finite"):  # the observation checks stay in front of the trace
        bundle.act({**singles[0], "proprio": np.full((3, 32), np.nan, np.float32)})
    assert np.array_equal(bundle.act_batch(batch), eager_batch)  # batches keep the eager network


# a config.json edit -> the words the loader's BundleError must contain (field and what is allowed)
HAND = {"lower": list(B.C.JOINT_LOWER), "upper": list(B.C.JOINT_UPPER)}
BAD_CONFIGS = [
    ("inverted limits", dict(joint_lower=HAND["upper"], joint_upper=HAND["lower"]),
     r"joint_lower must be < joint_upper at every joint \(joint 0: 0\.47 >= -0\.47"),
    ("limits past the hand", dict(joint_upper=[HAND["upper"][0] + 0.5, *HAND["upper"][1:]]),
     r"joint_upper lies outside the hand's joint limits.*joint 0: 0\.97 vs 0\.47"),
    ("non-finite limit", dict(joint_lower=[None, *HAND["lower"][1:]]), r"joint_lower must be a list of numbers"),
    ("too few limits", dict(joint_lower=HAND["lower"][:15]), r"must have 16 entries"),
    ("rate a loop cannot hold", dict(control_hz=1000.0), r"control_hz must be in \[5, 100\] Hz.*got 1000"),
    ("rate too slow", dict(control_hz=1.0), r"control_hz must be in \[5, 100\] Hz"),
    ("huge action scale", dict(action_scale=2.0), r"action_scale must be in \(0, 0\.25\] rad per step, got 2\.0"),
    ("negative action scale", dict(action_scale=-0.01), r"action_scale must be in \(0, 0\.25\]"),
    ("number as a string", dict(control_hz="20"), r"control_hz must be a number, got '20' \(str\)"),
    ("scale as a string", dict(action_scale="0.04"), r"action_scale must be a number, got '0\.04' \(str\)"),
    ("limit as a string", dict(joint_upper=["1.0", *HAND["upper"][1:]]), r"joint_upper must be a list of numbers"),
    ("bool as a number", dict(norm_clip=True), r"norm_clip must be a number, got True \(bool\)"),
    ("width as a string", dict(actor_hidden=["512", 256, 128]), r"actor_hidden must be a list of integers"),
    ("zero width", dict(actor_hidden=[512, 0, 128]), r"actor_hidden must hold sizes >= 1"),
    ("nested size as a string", dict(encoder={"in_dim": "9", "hidden": [256, 128], "latent_dim": 8}),
     r"encoder\.in_dim.*'9'"),
    ("network as a string", dict(encoder="big"), r"encoder must be a EnvFactorEncoderConfig \(a JSON object\) or "
                                                 r"null, got 'big'"),
    ("wrong action count", dict(action_dim=12), r"action_dim must be 16"),
    ("card not an object", dict(card=[1, 2]), r"card must be a JSON object"),
]


@pytest.mark.parametrize(("what", "changes", "match"), BAD_CONFIGS, ids=[c[0] for c in BAD_CONFIGS])
def test_loader_validates_every_field_before_use(tmp_path, teacher, what, changes, match):
    """A bundle is refused by the loader (so by evaluation, the demo and deploy alike) with the file, the field and
    what is allowed; never accepted to fail later (on a hand: after the motors are on)."""
    path = teacher.save(tmp_path / "b")
    edit_config(path, **changes)
    with pytest.raises(BundleError, match=match) as err:
        load_bundle(path)
    assert str(path / "config.json") in str(err.value)


def test_valid_edge_values_load(tmp_path, teacher):
    """The ranges are inclusive, and a bundle may narrow the hand's joint limits."""
    narrow = [lo + 0.1 for lo in HAND["lower"]]
    path = teacher.save(tmp_path / "b")
    edit_config(path, control_hz=10, action_scale=0.25, joint_lower=narrow)  # an int rate is a number too
    cfg = load_bundle(path).config
    assert cfg.control_hz == 10 and cfg.action_scale == 0.25 and cfg.joint_lower == tuple(narrow)
    edit_config(path, control_hz=100.0, action_scale=0.2)
    assert load_bundle(path).config.control_hz == 100.0


def test_networks_that_cannot_be_built_are_a_bundle_error(tmp_path, teacher):
    path = teacher.to_student().save(tmp_path / "s")
    cfg = json.loads((path / "config.json").read_text())
    cfg["adaptation"]["kernels"] = [29, 5, 5]  # longer than the 30-step history allows
    (path / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(BundleError, match="cannot be built.*too short for kernels"):
        load_bundle(path)
