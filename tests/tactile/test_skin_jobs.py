"""Sparsh-skin jobs on tiny simulated sessions (`rotate collect --skin`): the window dataset, a tiny pretraining run
that learns (and resumes exactly), and tiny probes that write their report (force, pose, joystick)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch

from envs.sensors.xela import NUM_TAXELS, REST, XelaSkin
from rotation.cli import main
from rotation.data.dataset import find_sessions
from rotation.data.skin import SkinWindows, shared_reader
from rotation.jobs import collect
from rotation.tactile.models.encoders import load_encoder
from rotation.tactile.pretrain import job as pretrain
from rotation.tactile.pretrain.state import load_checkpoint, read_checkpoint
from rotation.tactile.probes import job as probe
from rotation.tactile.ssl import param_groups, step_rng

STRIDE = 5


@pytest.fixture(scope="module")
def cup_sessions(tmp_path_factory):
    """4 sessions of 2 s of scripted cup play on the Xela hand (skin, skin_force, object_pose)."""
    out = tmp_path_factory.mktemp("skin_cup")
    collect.run(collect.Config(out=out, skin=True, policy="play", episodes=4, num_envs=4, episode_steps=40, seed=3,
                               progress=False))
    return out


@pytest.fixture(scope="module")
def joystick_sessions(tmp_path_factory):
    """3 sessions of 2 s of the hand playing with the joystick fixture (skin, skin_force, joystick)."""
    out = tmp_path_factory.mktemp("skin_joystick")
    collect.run(collect.Config(out=out, skin=True, task="joystick", policy="play", episodes=3, num_envs=3,
                               episode_steps=40, seed=4, progress=False))
    return out


def test_skin_windows_of_simulated_sessions(cup_sessions):
    paths = find_sessions(cup_sessions)
    ds = SkinWindows(paths, stride=STRIDE)
    assert set(ds.labels) == {"skin_force", "object_pose", "priv"} and len(ds) > 40
    item = ds[len(ds) // 2]
    assert item["skin"].shape == (10, NUM_TAXELS, 6) and item["xela_baseline"].shape == (NUM_TAXELS, 3)
    assert item["skin_force"].shape == (18, 3) and item["object_pose"].shape == (7,)
    s, row = (int(v) for v in ds.index[len(ds) // 2])
    r = shared_reader(paths[s])  # the dataset's own reader (a second handle on a SWMR file would disturb it)
    xela, pos = r.stream("skin/xela"), r.stream("skin/taxel_pos")
    # the window is the 10 frames ending at its end (100 Hz, no gap), counts and positions side by side
    assert float(item["time"]) == xela.timestamps[row]
    assert np.array_equal(item["skin"][..., :3].numpy(), xela.data[row - 9 : row + 1])
    assert np.array_equal(item["skin"][..., 3:].numpy(), pos.data[row - 9 : row + 1])
    # simulated sessions: the baseline is the simulated skin's rest reading under that episode's key
    sim = XelaSkin(1)
    sim.reset(np.zeros(1, np.int64), np.array([int(r.meta.extra["skin_key"])], dtype=np.uint64))
    assert np.allclose(ds.baselines[s], REST + sim.offset[0])
    # labels read without the skin equal the samples'
    forces = ds.labels_array("skin_force")
    assert forces.shape == (len(ds), 18, 3) and np.array_equal(forces[len(ds) // 2], item["skin_force"].numpy())
    # sequences: S windows ending every 0.1 s, labels per window
    seq = SkinWindows(paths, stride=STRIDE, sequence=3, labels=("object_pose",))
    first = seq[0]
    assert first["skin"].shape == (3, 10, NUM_TAXELS, 6) and first["object_pose"].shape == (3, 7)
    assert np.allclose(np.diff(first["time"].numpy()), 0.1) and len(seq) < len(ds)
    assert seq.labels_array("object_pose").shape == (len(seq), 3, 7)
    with pytest.raises(ValueError, match=r"label\(s\) \['joystick'\] are missing"):
        SkinWindows(paths, labels=("joystick",))


def tiny(tmp_path, sessions, **kw) -> pretrain.Config:
    """A tinier Sparsh-skin with a small head and 4 local views (not 8: time), on the CPU, no workers."""
    base = dict(encoder="skin", sessions=(sessions,), out=tmp_path / "run", size="tinier", stride=STRIDE, steps=4,
                batch_size=8, lr=1e-3, warmup_fraction=0.1, head_hidden=64, head_bottleneck=32, prototypes=64,
                stats_windows=64, num_workers=0, device="cpu", checkpoint_every=2, log_every=2, progress=False,
                torch_threads=1, skin=pretrain.SkinObjectiveConfig(num_local=4))
    return pretrain.Config(**{**base, **kw})


def _mean_loss(student, teacher, loss_fn, windows, cfg) -> float:
    """DINO + iBOT + KoLeo of ``student`` against ``teacher`` on fixed batches and views (eval mode)."""
    goal = pretrain.objective(cfg)
    grids = {"skin": (NUM_TAXELS,)}
    total = 0.0
    for i in range(2):
        batch = torch.utils.data.default_collate([windows[j] for j in range(i * 6, i * 6 + 6)])
        inputs = student.encoder.preprocess(batch)
        views = goal.views(grids, 6, step_rng(99, i), torch.device("cpu"))
        with torch.no_grad():
            total += float(goal.loss(loss_fn, goal.forward(student, teacher, inputs, views), cfg.teacher_temp)[0])
    return total / 2


def test_tiny_skin_pretraining_learns_and_resumes(tmp_path, cup_sessions):
    cfg = tiny(tmp_path / "a", cup_sessions, steps=8, checkpoint_every=4, log_every=4, batch_size=4)
    result = pretrain.run(cfg)
    out = cfg.out
    assert result["steps"] == 8 and len(result["history"]) == 2
    point = result["history"][-1]
    assert all(math.isfinite(point[k]) for k in ("loss", "loss_dino", "loss_ibot", "loss_koleo", "teacher_entropy"))
    assert pretrain.load_config(out / "config.json") == cfg and any((out / "tb").iterdir())
    enc = load_encoder(out)
    assert enc.token_interface.groups == (("skin", 368),) and enc.cfg.size == "tinier"
    assert float(enc.skin_div[2]) > 1.0  # the input statistics were fitted (counts, not the default 1)
    tensors, meta = read_checkpoint(out / "ckpt_000000008.safetensors")
    assert meta["encoder"]["kind"] == "skin" and {"dino.center", "ibot.center"} <= set(tensors)
    # learning: the trained student matches the final teacher better than the initial student does
    student, loss_fn = pretrain.build(cfg)
    student0, _ = pretrain.build(cfg)
    teacher = pretrain.build(cfg)[0]
    load_checkpoint(out / "ckpt_000000008.safetensors", student, teacher, loss_fn,
                    torch.optim.AdamW(param_groups([student], cfg.weight_decay)), meta["encoder"], "test")
    for name, buf in student0.named_buffers():
        buf.copy_(tensors[f"student.{name}"])
    for m in (student, student0, teacher):
        m.eval()
    windows = SkinWindows(find_sessions(cup_sessions), stride=STRIDE, labels=())
    before = _mean_loss(student0, teacher, loss_fn, windows, cfg)
    after = _mean_loss(student, teacher, loss_fn, windows, cfg)
    print(f"skin loss against the final teacher: initial student {before:.3f}, trained {after:.3f}")
    assert after < 0.9 * before, (before, after)
    # resume: a run stopped after its step-4 checkpoint ends where the uninterrupted one did, bit for bit
    b = tmp_path / "b"
    shutil.copytree(out, b)
    (b / "ckpt_000000008.safetensors").unlink()
    resumed = pretrain.run(dataclasses.replace(cfg, out=b, resume=True))
    assert resumed["steps"] == 8
    got, _ = read_checkpoint(b / "ckpt_000000008.safetensors")
    assert set(got) == set(tensors) and not [k for k in tensors if not torch.equal(tensors[k], got[k])]


def test_skin_pretraining_on_two_processes(tmp_path, cup_sessions):
    cfg = tiny(tmp_path, cup_sessions, steps=1, checkpoint_every=1, batch_size=2, nproc_per_node=2, stats_windows=8,
               skin=pretrain.SkinObjectiveConfig(num_local=2))
    assert pretrain.run(cfg)["exit_code"] == 0
    ranks = json.loads((cfg.out / "ranks.json").read_text())
    assert ranks["world_size"] == 2 and ranks["identical"]


def test_skin_pretraining_bad_input(tmp_path, cup_sessions, capsys):
    with pytest.raises(ValueError, match="cache: the skin encoder reads its windows from the sessions"):
        tiny(tmp_path, cup_sessions, cache=tmp_path / "cache")
    with pytest.raises(ValueError, match="modalities"):
        tiny(tmp_path, cup_sessions, modalities="img")
    with pytest.raises(ValueError, match="skin.local_scale"):
        tiny(tmp_path, cup_sessions, skin=pretrain.SkinObjectiveConfig(local_scale=(0.5, 0.2)))
    assert main(["pretrain", "--encoder", "skin", "--sessions", str(cup_sessions), "--skin.num-global", "0",
                 "--no-progress"]) == 2
    assert "skin.num_global" in capsys.readouterr().err


@pytest.fixture(scope="module")
def skin_checkpoint(tmp_path_factory):
    from rotation.tactile.models.sparsh_skin import SparshSkin, SparshSkinConfig, save_skin

    torch.manual_seed(0)
    return save_skin(SparshSkin(SparshSkinConfig(size="tinier")), tmp_path_factory.mktemp("skin_enc") / "e.safetensors")


def _probe(tmp_path, checkpoint, sessions, **kw) -> probe.Config:
    base = dict(encoder="skin", checkpoint=checkpoint, sessions=(sessions,), out=tmp_path / "probe",
                budgets=(0.5, 1.0), test_fraction=0.3, stride=2 * STRIDE, steps=2, batch_size=4, head_hidden=16,
                sequence_windows=2, num_workers=0, device="cpu", progress=False, torch_threads=1)
    return probe.Config(**{**base, **kw})


@pytest.mark.parametrize(("which", "tasks", "variants", "budgets"), [
    ("cup", {"force", "pose"}, ("pretrained", "e2e"), (0.5, 1.0)),
    ("joystick", {"force", "joystick"}, ("pretrained",), (1.0,)),
])
def test_tiny_skin_probes_write_their_report(tmp_path, cup_sessions, joystick_sessions, skin_checkpoint, which,
                                             tasks, variants, budgets):
    sessions = cup_sessions if which == "cup" else joystick_sessions
    kw = {} if variants == ("pretrained", "e2e") else {"variants": variants}  # the default: both
    cfg = _probe(tmp_path, skin_checkpoint, sessions, budgets=budgets, **kw)
    report = probe.run(cfg)
    data = json.loads((cfg.out / "results.json").read_text())
    assert data["rows"] == report["rows"] and {r["task"] for r in data["rows"]} == tasks
    metrics = {"force": {"rmse_x_N", "rmse_y_N", "rmse_z_N"}, "pose": {"rmse_position_m", "rmse_rotation_rad"},
               "joystick": {"rmse_roll_rad", "rmse_pitch_rad", "rmse_yaw_rad"}}
    want = {(t, v, b, m) for t in tasks for m in metrics[t] for v in variants for b in budgets}
    assert {(r["task"], r["variant"], r["budget"], r["metric"]) for r in data["rows"]} == want
    assert all(math.isfinite(r["value"]) and r["value"] >= 0 for r in data["rows"])
    assert {b["task"] for b in data["baselines"]} == tasks
    temporal = (tasks - {"force"}).pop()
    assert data["trace_plots"] == [f"{temporal}_over_time.png"]
    assert (cfg.out / f"{temporal}_over_time.png").stat().st_size > 10_000
    md = (cfg.out / "results.md").read_text()
    assert f"| task | metric | budget | {' | '.join(variants)} | baseline |" in md
    assert f"({temporal}_over_time.png)" in md


def test_skin_probe_bad_input(tmp_path, cup_sessions, skin_checkpoint):
    with pytest.raises(ValueError, match="variants: need distinct names among pretrained, e2e"):
        _probe(tmp_path, skin_checkpoint, cup_sessions, variants=("image_only",))
    with pytest.raises(ValueError, match="tasks: need distinct names among force, pose, joystick"):
        _probe(tmp_path, skin_checkpoint, cup_sessions, tasks=("slip",))
    with pytest.raises(ValueError, match=r"label\(s\) \['joystick'\] are missing"):
        probe.run(_probe(tmp_path, skin_checkpoint, cup_sessions, tasks=("joystick",)))
    with pytest.raises(ValueError, match="holds a skin encoder, not sparshx; pass --encoder skin"):
        probe.run(dataclasses.replace(_probe(tmp_path, skin_checkpoint, cup_sessions), encoder="sparshx"))
