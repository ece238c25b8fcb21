"""Imitation learning (rotation.il, `rotate train-il`, `rotate evaluate --task insertion`): the policy learns the
demonstrations' actions (the loss falls far below where it started, and would not without learning), resumes
exactly, round-trips as a bundle, ensembles its chunks over time, and runs in closed loop with touch."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from rotation.data.dataset import find_sessions
from rotation.il import job
from rotation.il.bundle import ILPolicy, load_il
from rotation.il.data import Demos
from rotation.il.model import ChunkPolicy, PolicyConfig
from rotation.il.rollout import wilson
from rotation.jobs import demos


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("il") / "demos"
    demos.run(demos.Config(episodes=2, out=out, seed=3, image_size=(48, 36), progress=False))
    return out


@pytest.fixture(scope="module")
def small_encoder(tmp_path_factory) -> str:
    """A Sparsh-X of the tinier size with one unimodal and one fusion layer, random weights: the touch path's
    plumbing at a fraction of the shipped encoder's cost (what the encoder's weights do is the benchmark's job)."""
    from rotation.tactile.models.encoders import ENCODERS

    torch.manual_seed(0)
    kind = ENCODERS["sparshx"]
    encoder = kind.build("tinier", ("img", "mic", "imu", "pressure"), "bottleneck", 0.0, (1, 1))
    return str(kind.save(encoder, tmp_path_factory.mktemp("encoder") / "encoder.safetensors"))


def _train(demo_dir, out, **kw):
    base = dict(demos=demo_dir, out=out, steps=160, batch_size=16, chunk=5, width=32, checkpoint_every=80,
                lr=1e-3, progress=False, torch_threads=1)
    return job.run(job.Config(**{**base, **kw}))


def test_the_policy_learns_the_demonstrations_and_resumes_exactly(demo_dir, tmp_path):
    result = _train(demo_dir, tmp_path / "full")
    trained = load_il(result["bundle"]).model
    untrained = ChunkPolicy(trained.cfg)
    untrained.load_state_dict({k: v for k, v in trained.state_dict().items() if "_mean" in k or "_std" in k},
                              strict=False)  # the same standardization, random weights
    data = Demos(find_sessions(demo_dir), trained.cfg.chunk)

    def loss(model) -> float:  # standardized L1 over every demonstrated chunk
        model.eval()
        with torch.no_grad():
            b = {k: torch.stack([data[i][k] for i in range(len(data))]) for k in ("image", "proprio", "actions",
                                                                                 "mask")}
            err = (model(b["image"], b["proprio"]) - (b["actions"] - model.action_mean) / model.action_std).abs()
            return float((err.mean(-1) * b["mask"]).sum() / b["mask"].sum())

    before, after = loss(untrained), loss(trained)
    assert after < 0.5 * before, (before, after)  # measured: about 0.8 -> 0.2
    part = tmp_path / "part"
    _train(demo_dir, part, steps=80)
    resumed = _train(demo_dir, part, resume=True)
    a, b = load_il(result["bundle"]), load_il(resumed["bundle"])
    for (name, x), y in zip(a.model.state_dict().items(), b.model.state_dict().values(), strict=True):
        assert torch.equal(x, y), name
    card = json.loads((tmp_path / "full" / "bundle" / "config.json").read_text())["card"]
    assert card["trained_by"] == "rotate train-il" and card["demonstrations"] == 2 and card["steps"] == 160
    assert a.meta["grip"] == "fingertips" and a.grip == "fingertips"  # its evaluation holds the plug the same way
    assert a.meta["wrist"] == "stiff" and a.wrist == "stiff"  # and moves the wrist the same way


def _mixing_is_refused(demo_dir, other, tmp_path, match):
    """Training on ``demo_dir`` with ``other``'s one demonstration beside it is refused with ``match``, before the
    run's folder is made."""
    import shutil

    mixed = tmp_path / f"mixed_{other.name}"
    shutil.copytree(demo_dir, mixed)
    [extra] = find_sessions(other)
    shutil.copy(extra, mixed / f"{other.name}_episode.h5")
    with pytest.raises(ValueError, match=match):
        _train(mixed, tmp_path / f"il_mixed_{other.name}", steps=2)
    assert not (tmp_path / f"il_mixed_{other.name}").exists()


def test_a_bundle_knows_its_grip_and_demonstrations_of_two_grips_are_refused(demo_dir, tmp_path):
    assert ILPolicy(ChunkPolicy(PolicyConfig()), {"task": "insertion"}).grip == "palm"  # bundles from before
    assert ILPolicy(ChunkPolicy(PolicyConfig()), {"task": "insertion"}).wrist == "stiff"
    palm = tmp_path / "palm"
    demos.run(demos.Config(episodes=1, out=palm, seed=4, image_size=(48, 36), grip="palm", progress=False))
    _mixing_is_refused(demo_dir, palm, tmp_path, "different grips")


def test_a_compliant_wrist_run_trains_and_evaluates_with_its_wrist_and_is_not_mixed(demo_dir, tmp_path):
    from rotation.cli import main

    soft = tmp_path / "soft"
    demos.run(demos.Config(episodes=1, out=soft, seed=6, image_size=(48, 36), wrist="compliant", progress=False))
    bundle = _train(soft, tmp_path / "il_soft", steps=2)["bundle"]
    assert load_il(bundle).wrist == "compliant"
    out = tmp_path / "eval"
    assert main(["evaluate", "--task", "insertion", "--policy", f"soft={bundle}", "--episodes", "1", "--seed", "900",
                 "--episode-steps", "4", "--out", str(out), "--no-progress"]) == 0
    [row] = json.loads((out / "results.json").read_text())["rows"]
    assert row["wrist"] == "compliant" and row["grip"] == "fingertips"
    _mixing_is_refused(demo_dir, soft, tmp_path, "move the wrist in different ways")


def test_the_policy_learns_the_actions_a_step_executes(demo_dir):
    """The sessions keep the expert's raw labels (here some beyond the step's limits: 3 mm and 2 degrees per axis);
    the training samples hold them clipped as the env's step clips them."""
    from rotation.data.session_reader import SessionReader

    paths = find_sessions(demo_dir)
    raw = []
    for path in paths:
        with SessionReader(path) as r:
            raw.append(r.stream("actions/wrist").data.copy())
    raw = np.concatenate(raw)
    assert np.abs(raw[:, :3]).max() > 0.003 and np.abs(raw[:, 3:]).max() > np.radians(2)
    data = Demos(paths, chunk=4)
    assert np.abs(data.actions[:, :3]).max() <= 0.003 + 1e-9
    assert np.abs(data.actions[:, 3:]).max() <= np.radians(2) + 1e-7
    inside = (np.abs(raw[:, :3]) < 0.003).all(1) & (np.abs(raw[:, 3:]) < np.radians(2)).all(1)
    assert inside.any() and np.array_equal(data.actions[inside], raw[inside])


def test_temporal_ensembling_averages_the_chunks_that_cover_a_step():
    model = ChunkPolicy(PolicyConfig(image_size=(32, 32), chunk=3, width=16, heads=2))
    outputs = iter([torch.tensor([[[1.0] * 6, [2.0] * 6, [3.0] * 6]]), torch.tensor([[[10.0] * 6] * 3])])
    model.forward = lambda *a: next(outputs)  # type: ignore[method-assign]
    policy = ILPolicy(model, {"touch": "none"})
    obs = {"image": np.zeros((32, 32, 3), np.uint8), "wrist": np.zeros(7), "joints": np.zeros(16)}
    assert policy.act(obs)[0] == pytest.approx(1.0)
    w = np.exp(-0.01 * np.arange(2))  # step 1: the first chunk's 2.0 (older, weight 1) and the second's 10.0
    assert policy.act(obs)[0] == pytest.approx((w[0] * 2.0 + w[1] * 10.0) / w.sum())


def test_a_touch_policy_runs_in_closed_loop_and_is_reported(demo_dir, small_encoder, tmp_path):
    from rotation.cli import main

    bundle = _train(demo_dir, tmp_path / "touch", touch="all", encoder=small_encoder, steps=2)["bundle"]
    out = tmp_path / "eval"
    assert main(["evaluate", "--task", "insertion", "--policy", f"touch={bundle}", "--episodes", "1", "--seed",
                 "900", "--episode-steps", "12", "--out", str(out), "--video", "--no-progress"]) == 0
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert [r["policy"] for r in rows] == ["touch"] and 0 <= rows[0]["success_rate"] <= 1
    assert rows[0]["touch"] == "all" and 1 <= rows[0]["trials"][0]["steps"] <= 12
    assert any((out / "videos").glob("touch_*.mp4")) and (out / "success.png").is_file()


def test_a_stopped_insertion_evaluation_continues_from_its_kept_trials(demo_dir, tmp_path):
    """Every finished trial is kept in trials.jsonl at once; the same evaluation run again into the same folder takes
    those and plays only the rest (a line cut by the stop is passed over), giving what one uninterrupted run gives;
    a trial another bundle played is not taken."""
    from rotation.cli import main

    bundle = _train(demo_dir, tmp_path / "camera", steps=2)["bundle"]
    other = _train(demo_dir, tmp_path / "other", steps=3)["bundle"]
    args = ["evaluate", "--task", "insertion", "--episodes", "2", "--seed", "900", "--episode-steps", "8",
            "--no-progress"]
    whole = tmp_path / "whole"
    assert main([*args, "--policy", f"cam={bundle}", "--out", str(whole)]) == 0
    lines = (whole / "trials.jsonl").read_text().splitlines()
    assert [json.loads(x)["seed"] for x in lines] == [900, 901]
    first = json.loads(lines[0])
    first["result"]["steps"] = 10_000  # marked, to see that the kept trial is taken rather than played again
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    (stopped / "trials.jsonl").write_text(json.dumps(first) + "\n" + lines[1][: len(lines[1]) // 2])
    assert main([*args, "--policy", f"cam={bundle}", "--out", str(stopped)]) == 0
    kept = json.loads((stopped / "results.json").read_text())["rows"][0]["trials"]
    played = json.loads((whole / "results.json").read_text())["rows"][0]["trials"]
    assert kept[0]["steps"] == 10_000 and kept[1] == played[1]
    assert main([*args, "--policy", f"cam={other}", "--out", str(stopped)]) == 0  # same name, other weights
    assert json.loads((stopped / "results.json").read_text())["rows"][0]["trials"][0]["steps"] <= 8


def test_an_end_to_end_touch_policy_trains_its_own_encoder_resumes_and_reloads_it(demo_dir, small_encoder, tmp_path):
    """--touch e2e: an encoder of the named one's structure, from random weights, trained with the policy on windows
    rendered per batch; the checkpoint and the bundle keep its weights, a resumed run matches an uninterrupted one."""
    from rotation.il.touch import TouchEmbedder
    from rotation.tactile.models.encoders import load_encoder

    kw = dict(touch="e2e", encoder=small_encoder, batch_size=2, checkpoint_every=2)
    full = _train(demo_dir, tmp_path / "full", steps=3, **kw)
    _train(demo_dir, tmp_path / "part", steps=2, **kw)
    resumed = _train(demo_dir, tmp_path / "part", steps=3, resume=True, **kw)
    trained = load_encoder(tmp_path / "full" / "bundle" / "touch_encoder.safetensors").state_dict()
    again = load_encoder(tmp_path / "part" / "bundle" / "touch_encoder.safetensors").state_dict()
    assert trained.keys() == again.keys() and all(torch.equal(trained[k], again[k]) for k in trained)
    fresh = TouchEmbedder(small_encoder, "e2e", seed=0).encoder.state_dict()  # the run's initial weights
    assert fresh.keys() == trained.keys()
    moved = [k for k in trained if not torch.equal(trained[k], fresh[k])]
    assert len(moved) > len(trained) // 2, "training left most of the encoder at its random initial weights"
    pretrained = dict(TouchEmbedder(small_encoder, "all").encoder.named_parameters())  # weights, not buffers
    weights = [k for k in pretrained if pretrained[k].ndim > 1]
    assert weights and not any(torch.allclose(trained[k], pretrained[k].to(trained[k].dtype)) for k in weights)
    policy = load_il(full["bundle"])
    assert policy.reads_touch and policy.touch_modalities == "e2e"
    assert policy.touch_encoder == str(tmp_path / "full" / "bundle" / "touch_encoder.safetensors")
    own = TouchEmbedder(policy.touch_encoder, "all").encoder  # what the closed loop reads: the bundle's own, frozen
    assert all(torch.equal(v, trained[k]) for k, v in own.state_dict().items()) and not own.training
    assert json.loads((tmp_path / "full" / "bundle" / "config.json").read_text())["touch"] == "e2e"
    assert resumed["history"][-1]["step"] == full["history"][-1]["step"] == 3


def test_a_skin_policy_learns_from_the_xela_hands_demonstrations_and_runs_on_that_hand(tmp_path):
    """The Sparsh-skin row: `rotate demos --hand xela_v4` records the skin (no Digit 360 streams), `train-il --touch
    skin` reads one embedding of the whole hand per step and records the hand, closed-loop evaluation runs it on
    that hand with the live skin window; touch and demonstrations of different hands are refused in one line."""
    from rotation.cli import main
    from rotation.data.session_reader import SessionReader
    from rotation.tactile.models.sparsh_skin import SparshSkin, SparshSkinConfig, save_skin

    out = tmp_path / "demos"
    demos.run(demos.Config(hand="xela_v4", episodes=1, out=out, seed=3, image_size=(48, 36), progress=False))
    [path] = find_sessions(out)
    with SessionReader(path) as r:
        assert r.has("skin/xela") and not any(n.startswith("digit360/") for n in r.names)
        assert r.meta.extra["sim_hand"] == "xela_v4" and "skin_key" in r.meta.extra
    torch.manual_seed(0)
    encoder = str(save_skin(SparshSkin(SparshSkinConfig(size="tinier")), tmp_path / "skin.safetensors"))
    result = _train(out, tmp_path / "il", touch="skin", encoder=encoder, steps=2)
    policy = load_il(result["bundle"])
    assert policy.meta["hand"] == "xela_v4" and policy.model.cfg.fingers == 1
    assert main(["evaluate", "--task", "insertion", "--policy", f"skin={result['bundle']}", "--episodes", "1",
                 "--seed", "900", "--episode-steps", "4", "--out", str(tmp_path / "eval"), "--no-progress"]) == 0
    [row] = json.loads((tmp_path / "eval" / "results.json").read_text())["rows"]
    assert row["hand"] == "xela_v4" and row["touch"] == "skin" and row["trials"][0]["steps"] == 4
    with pytest.raises(ValueError, match="needs a Digit 360 hand's demonstrations"):
        _train(out, tmp_path / "bad", touch="all")
    assert not (tmp_path / "bad").exists()  # refused before anything was written


def test_wilson_interval():
    lo, hi = wilson(9, 10)
    assert lo == pytest.approx(0.5958, abs=1e-3) and hi == pytest.approx(0.9821, abs=1e-3)
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == pytest.approx(1.0)


def test_dagger_rollouts_record_the_experts_labels_on_the_states_the_policy_reaches(demo_dir, tmp_path, capsys):
    """`rotate demos --policy`: the policy drives (or, with probability beta, the expert), the session records what
    the expert run alongside chose on each frame, reproduced here by a fresh expert fed the recorded states; beta 1
    is the plain expert's demonstration; a rerun keeps the files, other weights are refused."""
    from envs.insertion import InsertionConfig
    from envs.insertion_expert import ExpertConfig, InsertionExpert
    from rotation.cli import main
    from rotation.data.session_reader import SessionReader

    bundle = _train(demo_dir, tmp_path / "pol", steps=40)["bundle"]
    base = dict(episodes=1, seed=9, image_size=(48, 36), episode_steps=30, expert_align="state", progress=False)
    driven = tmp_path / "dagger"
    assert demos.run(demos.Config(out=driven, policy=str(bundle), **base))["episodes"] == 1

    def read(out):
        with SessionReader(find_sessions(out)[0]) as r:
            return (r.meta.properties, r.meta.extra, {k: r.stream(k).data.copy() for k in (
                "actions/wrist", "wrist/pose", "labels/socket", "labels/prong", "labels/socket_force")})

    props, extra, s = read(driven)
    assert props["policy_steps"] == props["steps"] == len(s["actions/wrist"]) and extra["policy_sha256"]
    expert = InsertionExpert(InsertionConfig(image_size=(48, 36)), 9 * 1_000_000, ExpertConfig(align="state"))
    for i, label in enumerate(s["actions/wrist"]):
        obs = {"socket": s["labels/socket"][i], "prong": s["labels/prong"][i]}
        assert np.allclose(expert.act(obs, {"force": float(s["labels/socket_force"][i, 0])}), label, atol=1e-6), i
    # the wrist moved by the policy's actions, not by the recorded labels
    moved = np.diff(s["wrist/pose"][:, :3], axis=0)
    assert np.abs(moved - np.clip(s["actions/wrist"][:-1, :3], -0.003, 0.003)).max() > 1e-4
    assert demos.run(demos.Config(out=driven, policy=str(bundle), **base))["episodes"] == 0  # kept
    # a round ends its episode once the plug has moved slip_stop in the hand (here at once: 0.1 mm)
    stopped = tmp_path / "stopped"
    demos.run(demos.Config(out=stopped, policy=str(bundle), slip_stop=1e-4, **base))
    short = read(stopped)[0]
    assert short["slipped"] and short["steps"] == len(read(stopped)[2]["actions/wrist"]) < props["steps"]
    with pytest.raises(ValueError, match="slip_stop"):
        demos.Config(out=tmp_path / "y", policy=str(bundle), slip_stop=0.1)
    plain, mixed = tmp_path / "plain", tmp_path / "mixed"
    demos.run(demos.Config(out=plain, **base))
    demos.run(demos.Config(out=mixed, policy=str(bundle), beta=1.0, **base))
    assert read(mixed)[0]["policy_steps"] == 0
    assert np.array_equal(read(mixed)[2]["actions/wrist"], read(plain)[2]["actions/wrist"])
    other = _train(demo_dir, tmp_path / "pol2", steps=40, seed=1)["bundle"]
    args = ["demos", "--episodes", "1", "--seed", "9", "--image-size", "48", "36", "--episode-steps", "30",
            "--expert-align", "state", "--out", str(driven)]
    assert main([*args, "--policy", str(other)]) == 1
    assert "another run's demonstration" in capsys.readouterr().err
    assert main(["demos", "--beta", "0.5", "--out", str(tmp_path / "x")]) == 2
    assert "give --policy" in capsys.readouterr().err
    assert main(["demos", "--policy", str(bundle), "--out", str(tmp_path / "x")]) == 2  # trained on 48 x 36
    assert "camera size" in capsys.readouterr().err and not (tmp_path / "x").exists()
    # the next round's policy trains on both folders (a folder given twice, or inside another, counts once)
    _train((demo_dir, driven, driven), tmp_path / "round1", steps=2)
    card = json.loads((tmp_path / "round1" / "bundle" / "config.json").read_text())["card"]
    assert card["demonstrations"] == 3
    assert main(["train-il", "--demos", str(demo_dir), str(tmp_path / "none"), "--out", str(tmp_path / "r2")]) == 1
    assert "no demonstration sessions in" in capsys.readouterr().err
