"""`rotate pretrain` and the window cache: the cache equals the reader, a tiny run learns, resume is exact, two
processes (gloo) stay identical, bad input is a clear error."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from rotation.cli import main
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.data.window_cache import SHARD_DONE, CachedWindows, build_cache, shard_name
from rotation.tactile.models.encoders import load_encoder
from rotation.tactile.models.sparshx_inputs import window_inputs
from rotation.tactile.pretrain import job as pretrain
from rotation.tactile.pretrain.state import load_checkpoint, read_checkpoint
from rotation.tactile.ssl import param_groups, sample_views, step_rng


def tiny(tmp_path, cache, sessions, stride, **kw) -> pretrain.Config:
    """A tinier Sparsh-X on IMU + pressure (cheap tokens), a small head, CPU, no workers."""
    base = dict(sessions=(sessions,), cache=cache, out=tmp_path / "run", size="tinier", modalities="imu,pressure",
                stride=stride, steps=4, batch_size=8, lr=1e-3, warmup_fraction=0.1, head_hidden=64,
                head_bottleneck=32, prototypes=64, stats_windows=32, num_workers=0, device="cpu",
                checkpoint_every=2, log_every=2, progress=False, torch_threads=1)
    return pretrain.Config(**{**base, **kw})


def test_cache_equals_the_reader_and_resumes(touch_sessions, touch_cache, cache_stride):
    paths = find_sessions(touch_sessions)
    cached = CachedWindows(touch_cache)
    live = TouchWindows([p.resolve() for p in paths], stride=cache_stride, audio_features=True)
    assert len(cached) == len(live) > 100 and cached.labels == live.labels
    assert np.array_equal(cached.index[:, :2], live.index[:, :2]) and np.array_equal(cached.end_times, live.end_times)
    for i in (0, 17, len(live) - 1):
        a, b = cached[i], live[i]
        assert a["image"].shape == (2, 224, 224, 3) and a["image"].dtype == torch.uint8
        ia = window_inputs({"image": a["image"][None]}, ["img"])["img"][0]
        assert torch.equal(ia, b["image"])  # exact: uint8 frames packed as the reader packs them
        assert torch.equal(a["imu"], b["imu"]) and torch.equal(a["pressure"], b["pressure"])
        assert a["audio"].dtype == torch.float16 and (a["audio"].float() - b["audio"]).abs().max() < 0.02
        for name in live.labels:
            assert torch.equal(a[name], b[name]), name
        assert int(a["finger"]) == int(b["finger"]) and float(a["time"]) == float(b["time"])
    # complete shards are kept; settings that differ are refused
    done = touch_cache / shard_name(paths[0].resolve()) / SHARD_DONE
    stamp = done.stat().st_mtime_ns
    build_cache([touch_sessions], touch_cache, stride=cache_stride, progress=False)
    assert done.stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match=r"other settings \(stride: 3 -> 4\)"):
        build_cache([touch_sessions], touch_cache, stride=4, progress=False)
    sub = CachedWindows(touch_cache, sessions=paths[:2])
    assert sub.paths == [p.resolve() for p in paths[:2]] and len(sub) < len(cached)


def _mean_loss(student, teacher, loss_fn, cache, cfg) -> float:
    """DINO loss of ``student`` against ``teacher`` on fixed batches and masks (eval mode: no drop path)."""
    ds = CachedWindows(cache)
    grids = {m: g for m, g in zip(("imu", "pressure"), ((56,), (56,)), strict=True)}
    total = 0.0
    for i in range(4):
        batch = torch.utils.data.default_collate([ds[j] for j in range(i * 8, i * 8 + 8)])
        inputs = student.encoder.preprocess(batch)
        views = sample_views(grids, 8, cfg.mask, step_rng(99, i))
        with torch.no_grad():
            t = {n: x[0] for n, x in teacher(inputs, views[:1]).items()}
            total += float(loss_fn(student(inputs, views), t, cfg.teacher_temp)[0])
    return total / 4


def test_tiny_pretraining_learns_and_writes_its_outputs(tmp_path, touch_sessions, touch_cache, cache_stride):
    cfg = tiny(tmp_path, touch_cache, touch_sessions, cache_stride, steps=16, checkpoint_every=8, log_every=4)
    result = pretrain.run(cfg)
    out = cfg.out
    assert result["steps"] == 16 and len(result["history"]) == 4
    assert all(np.isfinite(h["loss"]) and h["samples_per_s"] > 0 for h in result["history"])
    assert sorted(p.name for p in out.glob("ckpt_*.safetensors")) == ["ckpt_000000008.safetensors",
                                                                      "ckpt_000000016.safetensors"]
    assert pretrain.load_config(out / "config.json") == cfg
    assert any((out / "tb").iterdir())
    enc = load_encoder(out)  # the teacher's encoder, loaded strictly by the model's own loader
    assert enc.token_interface.names == ("imu", "pressure") and enc.cfg.size == "tinier"
    # learning: the trained student matches the final teacher's targets better than the initial student does
    student, loss_fn = pretrain.build(cfg)
    student0, _ = pretrain.build(cfg)
    teacher = pretrain.build(cfg)[0]
    tensors, meta = read_checkpoint(out / "ckpt_000000016.safetensors")
    assert meta["step"] == 16 and meta["encoder"]["kind"] == "sparshx"
    opt = torch.optim.AdamW(param_groups([student], cfg.weight_decay))
    load_checkpoint(out / "ckpt_000000016.safetensors", student, teacher, loss_fn, opt, meta["encoder"], "test")
    for name, buf in student0.named_buffers():  # the initial student with the fitted input statistics
        buf.copy_(tensors[f"student.{name}"])
    for m in (student, student0, teacher):
        m.eval()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        before = _mean_loss(student0, teacher, loss_fn, touch_cache, cfg)
        after = _mean_loss(student, teacher, loss_fn, touch_cache, cfg)
    finally:
        torch.set_num_threads(threads)
    print(f"DINO loss against the final teacher: initial student {before:.3f}, trained {after:.3f}")
    assert after < 0.9 * before, (before, after)
    assert torch.equal(tensors["student.encoder.imu_div"], student.encoder.imu_div)


def test_resume_is_bit_identical(tmp_path, touch_sessions, touch_cache, cache_stride):
    cfg = tiny(tmp_path / "a", touch_cache, touch_sessions, cache_stride, steps=4, checkpoint_every=2, drop_path=0.2)
    pretrain.run(cfg)
    b = tmp_path / "b"
    shutil.copytree(cfg.out, b)
    (b / "ckpt_000000004.safetensors").unlink()  # as if the run had stopped after its step-2 checkpoint
    resumed = pretrain.run(dataclasses.replace(cfg, out=b, resume=True))
    assert resumed["steps"] == 4 and resumed["history"][0]["step"] == 4
    want, meta_a = read_checkpoint(cfg.out / "ckpt_000000004.safetensors")
    got, meta_b = read_checkpoint(b / "ckpt_000000004.safetensors")
    assert set(want) == set(got) and any(k.startswith("optim.") for k in want)
    different = [k for k in want if not torch.equal(want[k], got[k])]
    assert not different, different[:5]
    assert meta_a["step"] == meta_b["step"] == 4 and meta_a["param_groups"] == meta_b["param_groups"]
    # a finished run resumed again has nothing left to do; a changed training setting is refused
    assert pretrain.run(dataclasses.replace(cfg, out=b, resume=True))["steps"] == 4
    with pytest.raises(ValueError, match=r"differs from the one saved .* in \['lr'\]"):
        pretrain.run(dataclasses.replace(cfg, out=b, resume=True, lr=2e-3))



def test_a_checkpoint_another_run_wrote_is_refused(tmp_path, touch_sessions, touch_cache, cache_stride):
    """--resume adopts the newest checkpoint in --out only if its metadata carries this run's id (run.json; a
    copied run folder is the same run): another run's checkpoint copied in is refused, and nothing changes."""
    from envs.errors import RequestRefused

    mine = tiny(tmp_path / "a", touch_cache, touch_sessions, cache_stride, steps=2, checkpoint_every=2)
    other = tiny(tmp_path / "c", touch_cache, touch_sessions, cache_stride, steps=4, checkpoint_every=4, seed=5)
    pretrain.run(mine)
    pretrain.run(other)
    shutil.copy(other.out / "ckpt_000000004.safetensors", mine.out / "ckpt_000000004.safetensors")
    before = {p: p.read_bytes() for p in mine.out.rglob("*") if p.is_file()}
    with pytest.raises(RequestRefused, match="is not a checkpoint this run wrote"):
        pretrain.run(dataclasses.replace(mine, resume=True))
    assert {p: p.read_bytes() for p in mine.out.rglob("*") if p.is_file()} == before

def test_two_processes_stay_identical(tmp_path, touch_sessions, touch_cache, cache_stride):
    cfg = tiny(tmp_path, touch_cache, touch_sessions, cache_stride, steps=3, checkpoint_every=3, batch_size=4,
               nproc_per_node=2)
    result = pretrain.run(cfg)
    assert result["exit_code"] == 0
    ranks = json.loads((cfg.out / "ranks.json").read_text())
    assert ranks["world_size"] == 2 and ranks["identical"] and len(set(ranks["student_sha256"])) == 1
    _, meta = read_checkpoint(cfg.out / "ckpt_000000003.safetensors")
    assert meta["world_size"] == 2 and meta["step"] == 3


def test_bad_input_is_a_clear_error(tmp_path, touch_sessions, touch_cache, capsys, cache_stride):
    with pytest.raises(ValueError, match="size: unknown size 'huge'"):
        tiny(tmp_path, touch_cache, touch_sessions, cache_stride, size="huge")
    with pytest.raises(ValueError, match="modalities"):
        tiny(tmp_path, touch_cache, touch_sessions, cache_stride, modalities="img,smell")
    with pytest.raises(ValueError, match="no checkpoint"):
        pretrain.run(tiny(tmp_path, touch_cache, touch_sessions, cache_stride, resume=True))
    with pytest.raises(ValueError, match="no session file or directory at .*missing"):
        pretrain.run(tiny(tmp_path, touch_cache, tmp_path / "missing", cache_stride))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"no session files \(\*\.h5\) in .*empty"):
        pretrain.run(tiny(tmp_path, touch_cache, tmp_path / "empty", cache_stride))
    # a checkpoint of another size or modality set names the file and both encoders
    cfg = tiny(tmp_path, touch_cache, touch_sessions, cache_stride, steps=2)
    pretrain.run(cfg)
    other = dataclasses.replace(cfg, modalities="imu")
    student, loss_fn = pretrain.build(other)
    teacher = pretrain.build(other)[0]
    meta = {"kind": "sparshx", "config": dataclasses.asdict(student.encoder.cfg)}
    meta["config"]["modalities"] = list(meta["config"]["modalities"])
    with pytest.raises(ValueError, match=r"ckpt_000000002\.safetensors holds an encoder .*'imu', 'pressure'"):
        load_checkpoint(cfg.out / "ckpt_000000002.safetensors", student, teacher, loss_fn,
                        torch.optim.AdamW(param_groups([student], 0.0)), meta, "tinier imu")
    # non-finite windows: the error names the session file
    bad_cache = tmp_path / "bad_cache"
    shutil.copytree(touch_cache, bad_cache)
    shard = sorted(p for p in bad_cache.iterdir() if p.is_dir())[0]
    imu = np.load(shard / "imu.npy", mmap_mode="r+")
    imu[:] = np.nan
    imu.flush()
    with pytest.raises(ValueError, match=r"non-finite .*'imu'.*; the batch holds windows of .*episode_00000\d\.h5"):
        pretrain.run(tiny(tmp_path / "nan", bad_cache, touch_sessions, cache_stride, stats_windows=8, batch_size=48))
    # the command line: one line, exit status 2
    assert main(["pretrain", "--sessions", str(touch_sessions), "--size", "huge", "--no-progress"]) == 2
    assert "size: unknown size 'huge'" in capsys.readouterr().err


def test_a_faster_encoder_by_its_layer_counts(tmp_path, touch_sessions, touch_cache, cache_stride):
    """--unimodal-layers / --fusion-layers build a Sparsh-X of that depth, which a fresh copy (the probes' and the
    ladder's end-to-end baselines) keeps; the skin encoder and an encoder without layers are refused."""
    from rotation.tactile.models.encoders import ENCODERS

    cfg = tiny(tmp_path, touch_cache, touch_sessions, cache_stride, unimodal_layers=3, fusion_layers=1)
    student, _ = pretrain.build(cfg)
    enc = student.encoder
    assert (enc.cfg.num_unimodal, enc.cfg.depth) == (3, 4)
    assert ENCODERS["sparshx"].rebuild(enc).cfg == enc.cfg
    default = pretrain.build(tiny(tmp_path, touch_cache, touch_sessions, cache_stride))[0].encoder
    count = sum(p.numel() for p in enc.parameters())
    assert count < 0.6 * sum(p.numel() for p in default.parameters())  # 4 of tinier's 8 layers
    with pytest.raises(ValueError, match="at least one layer"):
        tiny(tmp_path, touch_cache, touch_sessions, cache_stride, unimodal_layers=0, fusion_layers=0)
    with pytest.raises(ValueError, match="layers: the skin encoder"):
        ENCODERS["skin"].build("tinier", ("skin",), "bottleneck", 0.0, (3, 1))


def test_a_stop_signal_saves_then_stops(tmp_path, touch_sessions, touch_cache, monkeypatch, cache_stride):
    from rotation.interrupt import Interrupted

    class Stopped:  # as if Ctrl-C arrived during the first step
        requested, signum = True, 2

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

    monkeypatch.setattr(pretrain, "StopSignals", Stopped)
    cfg = tiny(tmp_path, touch_cache, touch_sessions, cache_stride, steps=4, checkpoint_every=4)
    with pytest.raises(Interrupted, match="stopped at step 1; --resume continues") as err:
        pretrain.run(cfg)
    assert err.value.exit_code == 130
    assert [p.name for p in cfg.out.glob("ckpt_*")] == ["ckpt_000000001.safetensors"]
    assert (cfg.out / "encoder.safetensors").is_file()


def test_sigterm_to_the_process_group_saves_with_loader_workers(tmp_path, touch_sessions, touch_cache, cache_stride):
    """`timeout`, `kill -- -PGID` and Ctrl-C signal the whole process group, loader workers included: the run
    still stops after its step, saves a checkpoint and the encoder, and exits with 143 without a traceback."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "rotation.cli", "pretrain", "--sessions", str(touch_sessions), "--cache",
           str(touch_cache), "--stride", str(cache_stride), "--size", "tinier", "--modalities", "imu,pressure",
           "--steps", "100000", "--batch-size", "8", "--head-hidden", "64", "--head-bottleneck", "32",
           "--prototypes", "64", "--stats-windows", "32", "--num-workers", "2", "--device", "cpu",
           "--checkpoint-every", "100000", "--log-every", "2", "--torch-threads", "1", "--no-progress",
           "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not list((out / "tb").glob("events.*")) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        time.sleep(1.0)  # a few steps in: the workers are loading batches
        assert proc.poll() is None, proc.communicate()[1]
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "--resume continues" in err
    assert len(list(out.glob("ckpt_*.safetensors"))) == 1 and (out / "encoder.safetensors").is_file()


def test_an_encoder_whose_layers_fuse_nothing_is_named_before_pretraining(tmp_path, touch_sessions, touch_cache,
                                                                            cache_stride, caplog):
    """`rotate pretrain` with one bottleneck fusion layer (3 + 1, the shipped tinier encoder's) warns that no
    modality's tokens will depend on another's; two fusion layers do not warn."""
    import logging

    with caplog.at_level(logging.WARNING):
        pretrain.build(tiny(tmp_path, touch_cache, touch_sessions, cache_stride, unimodal_layers=3, fusion_layers=1))
    assert "3 unimodal + 1 bottleneck fusion layer(s) fuse nothing" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        pretrain.build(tiny(tmp_path, touch_cache, touch_sessions, cache_stride, unimodal_layers=2, fusion_layers=2))
    assert "fuse nothing" not in caplog.text
