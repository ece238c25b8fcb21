"""Adapter ensembles: the weighted sum of the members' corrections exactly, members found inside the ensemble's
directory, checked as adapters are, clear errors for a bad config, evaluation with an ensemble."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from adapters.bundle import TouchUnavailable, build_adapted
from adapters.ensemble import EnsemblePolicy, load_ensemble, shares_unimodal
from adapters.ensemble_config import CorrectionGate
from rotation.bundles import load_bundle, weights_digest
from rotation.cli import main
from rotation.evaluate import job
from rotation.policy.bundle_config import BundleError

ENCODER = "sparshx-tinier-sim"


def _member(path, modalities, seed):
    """A member adapter with a non-zero correction."""
    policy = build_adapted("student", ENCODER, modalities, seed=seed)
    torch.manual_seed(seed)
    torch.nn.init.normal_(policy.adapter.zero.weight, std=0.05)
    torch.nn.init.normal_(policy.adapter.zero.bias, std=0.05)
    return policy.save(path)


@pytest.fixture(scope="module")
def ensemble_dir(tmp_path_factory):
    """An ensemble (`rotate ensemble-adapters`) whose two members (pressure; IMU + pressure) were copied into it."""
    tmp = tmp_path_factory.mktemp("ensemble")
    first = _member(tmp / "pressure", ("pressure",), seed=1)
    second = _member(tmp / "imu_pressure", ("imu", "pressure"), seed=2)
    out = tmp / "ens"
    assert main(["ensemble-adapters", "--members", str(first), str(second), "--weights", "0.25", "0.75",
                 "--touch-every", "3", "--out", str(out)]) == 0
    shutil.rmtree(first)  # the bundle stands alone
    shutil.rmtree(second)
    return out


def test_the_correction_is_the_weighted_sum_of_the_members(ensemble_dir, env_obs):
    env, obs = env_obs
    ens = load_bundle(ensemble_dir)
    assert isinstance(ens, EnsemblePolicy)
    assert ens.windows == ("pressure", "imu") and ens.touch_every == 3 and ens.fingers == ("index", "middle", "ring",
                                                                                           "thumb")
    assert "imu, pressure" in ens.config.touch_encoder and ens.config.adapter == str(ensemble_dir)
    groups = {k: obs[k] for k in ens.config.obs_groups}
    corr = ens.correction(ens.env_windows(obs), groups)
    parts = [load_bundle(ensemble_dir / "members" / name) for name in ("pressure", "imu_pressure")]
    want = [p.correction(p.env_windows(obs), groups) for p in parts]
    assert np.abs(want[0]).max() > 0 and np.abs(want[1]).max() > 0
    np.testing.assert_allclose(corr, 0.25 * want[0] + 0.75 * want[1], rtol=0, atol=1e-6)
    # it acts as the student with that correction, and without one exactly as the student
    student = load_bundle("student")
    assert np.array_equal(ens.act_batch(groups), student.act_batch(groups))
    assert np.array_equal(ens.act_batch(groups, correction=corr), parts[0].act_batch(groups, correction=corr))
    one = {k: v[0] for k, v in groups.items()}
    eager = ens.act(one, correction=corr[0])
    ens.prepare_realtime()  # deploy's traced paths: the same numbers
    assert np.array_equal(ens.correction(ens.env_windows(obs), groups), corr)
    assert np.array_equal(ens.act(one, correction=corr[0]), eager)


def test_per_dimension_weights_give_each_member_its_own_directions(ensemble_dir, env_obs, tmp_path):
    """--dim-weights: member k's correction of latent dimension d is weighted weight_k x dim_weights_k[d]."""
    env, obs = env_obs
    members = [str(ensemble_dir / "members" / name) for name in ("pressure", "imu_pressure")]
    first = [1.0, 0.0, 0.25, 1.0, 0.5, 0.0, 2.0, 1.0]
    second = [0.0, 1.0, 0.75, 0.5, 0.5, 1.0, 0.0, 1.0]
    out = tmp_path / "dims"
    assert main(["ensemble-adapters", "--members", *members, "--weights", "1", "0.5",
                 "--dim-weights", *map(str, first + second), "--out", str(out)]) == 0
    config = json.loads((out / "config.json").read_text())
    assert [m["dim_weights"] for m in config["members"]] == [first, second]
    # the card names the touch delay each member trained with (these fresh members trained with none)
    assert set(config["card"]["member_touch_delays"].values()) == {"none recorded"}
    ens = load_bundle(out)
    groups = {k: obs[k] for k in ens.config.obs_groups}
    corr = ens.correction(ens.env_windows(obs), groups)
    parts = [load_bundle(m) for m in members]
    want = [p.correction(p.env_windows(obs), groups) for p in parts]
    np.testing.assert_allclose(corr, np.array(first) * want[0] + 0.5 * np.array(second) * want[1], rtol=0, atol=1e-6)
    assert np.array_equal(corr[:, 1], (0.5 * torch.as_tensor(want[1][:, 1])).numpy())  # the first member's 0
    # a config without dim_weights (written before they existed): every dimension takes the member's weight
    old = tmp_path / "old"
    shutil.copytree(ensemble_dir / "members", old / "members")
    (old / "config.json").write_text(json.dumps({"kind": "adapter-ensemble", "format_version": 1, "members": [
        {"adapter": "members/pressure", "weight": 0.5}]}))
    np.testing.assert_allclose(load_bundle(old).correction(ens.env_windows(obs), groups), 0.5 * want[0], rtol=0,
                               atol=1e-6)


def test_a_gate_scales_its_dimensions_by_what_the_correction_reads():
    """g = clip(signal . c / width, 0, 1) per sample multiplies the gated dimensions' correction; the other
    dimensions are untouched, and a zero correction (adapters at initialization) stays exactly zero."""
    gate = CorrectionGate(dims=(1,), signal=(0, 0, 0, -1, -1, 0, 0, 0), width=0.2)
    c = torch.zeros(4, 8)
    c[:, 1] = -0.3
    c[:, 3] = torch.tensor([-0.5, -0.05, 0.0, 0.4])  # z[3] + z[4]: -0.6 (open), -0.1 (half), 0 and +0.6 (shut)
    c[:, 4] = torch.tensor([-0.1, -0.05, 0.0, 0.2])
    c[:, 6] = 0.7
    out = gate.apply(c)
    np.testing.assert_allclose(out[:, 1].numpy(), [-0.3, -0.15, 0.0, 0.0], rtol=0, atol=1e-7)
    keep = [d for d in range(8) if d != 1]
    assert torch.equal(out[:, keep], c[:, keep]) and c[1, 1] == -0.3  # the input is not modified
    zero = torch.zeros(3, 8)
    assert torch.equal(gate.apply(zero), zero)


def test_a_gated_ensemble_is_the_ungated_one_with_its_gate(ensemble_dir, env_obs, tmp_path):
    """`--gate-dims/--gate-signal/--gate-width` write the gate into config.json; the loaded ensemble's correction
    is the same members' ungated correction with the gate applied, in evaluation and in deploy's traced path."""
    env, obs = env_obs
    members = [str(ensemble_dir / "members" / name) for name in ("pressure", "imu_pressure")]
    plain = load_bundle(ensemble_dir)
    groups = {k: obs[k] for k in plain.config.obs_groups}
    ungated = plain.correction(plain.env_windows(obs), groups)
    signal = ungated[:, 3] + ungated[:, 4]
    assert np.abs(signal).max() > 0
    sign = 1.0 if signal.max() > 0 else -1.0  # the gate opens on a positive signal: point it at the samples' side
    signal = sign * signal
    width = float(2 * np.abs(signal).max())  # every sample's gate strictly between 0 and 1 where the signal is > 0
    out = tmp_path / "gated"
    assert main(["ensemble-adapters", "--members", *members, "--weights", "0.25", "0.75", "--touch-every", "3",
                 "--gate-dims", "0", "2", "--gate-signal", "0", "0", "0", str(sign), str(sign), "0", "0", "0",
                 "--gate-width", str(width), "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["gate"] == {
        "dims": [0, 2], "signal": [0.0, 0.0, 0.0, sign, sign, 0.0, 0.0, 0.0], "width": width}
    gated = load_bundle(out)
    corr = gated.correction(gated.env_windows(obs), groups)
    g = np.clip(signal / width, 0.0, 1.0)
    assert 0 < g.max() < 1  # the gate really scales the samples here
    want = ungated.copy()
    want[:, [0, 2]] *= g[:, None]
    np.testing.assert_allclose(corr, want, rtol=0, atol=1e-6)
    assert np.array_equal(corr[:, [1, 3, 4, 5, 6, 7]], ungated[:, [1, 3, 4, 5, 6, 7]])
    gated.prepare_realtime()
    assert np.array_equal(gated.correction(gated.env_windows(obs), groups), corr)
    assert weights_digest(str(out)) != weights_digest(str(ensemble_dir))  # the gate is part of its identity


def test_bad_gates_are_refused(ensemble_dir, tmp_path, capsys):
    member = str(ensemble_dir / "members" / "pressure")
    signal = ["0", "0", "0", "-1", "-1", "0", "0", "0"]
    cases = [
        (["--gate-dims", "1"], "--gate-dims and --gate-signal go together"),
        (["--gate-signal", *signal], "--gate-dims and --gate-signal go together"),
        (["--gate-dims", "3", "--gate-signal", *signal], "none of the gated ones [3]"),
        (["--gate-dims", "1", "1", "--gate-signal", *signal], "--gate-dims must be distinct"),
        (["--gate-dims", "1", "--gate-signal", *["0"] * 8], "--gate-signal must read some dimension"),
        (["--gate-dims", "1", "--gate-signal", *signal, "--gate-width", "0"], "--gate-width must be a number in"),
        (["--gate-dims", "-1", "--gate-signal", *signal], "--gate-dims must be distinct latent dimensions"),
        (["--gate-dims", "1", "--gate-signal", *signal, "0"], "gate signal must be 8 finite numbers"),
    ]
    for extra, message in cases:
        status = main(["ensemble-adapters", "--members", member, *extra, "--out", str(tmp_path / "e")])
        err = capsys.readouterr().err
        assert status == 2 and message in err and "Traceback" not in err, (extra, err)
        assert not (tmp_path / "e" / "config.json").exists()
    # the same checks when a hand-written config.json is loaded
    path = tmp_path / "hand"
    shutil.copytree(ensemble_dir / "members", path / "members")
    good = {"dims": [1], "signal": [0, 0, 0, -1, -1, 0, 0, 0], "width": 0.2}
    for gate, message in (({**good, "dims": [8]}, "gate dims must be distinct latent dimensions in"),
                          ({**good, "signal": [0.0] * 7 + [float("nan")]}, "gate signal must be 8 finite"),
                          ({**good, "width": -1}, "gate width must be a number in"),
                          ({**good, "gain": 2}, "unknown config keys"),
                          (5, "ensemble gate must be")):
        (path / "config.json").write_text(json.dumps({"kind": "adapter-ensemble", "format_version": 1, "members": [
            {"adapter": "members/pressure", "weight": 1.0}], "gate": gate}))
        with pytest.raises(BundleError, match=message):
            load_bundle(path)


def test_members_share_the_first_members_unimodal_layers(ensemble_dir, env_obs, tmp_path):
    """A member whose modalities are among the first member's, on the same encoder weights, starts from the first
    member's unimodal pass: the same tokens bit for bit, one pass of those layers instead of two."""
    env, obs = env_obs
    members = [str(ensemble_dir / "members" / name) for name in ("imu_pressure", "pressure")]
    out = tmp_path / "shared"
    assert main(["ensemble-adapters", "--members", *members, "--weights", "0.5", "1.5", "--out", str(out)]) == 0
    ens = load_bundle(out)
    assert ens.shares == (False, True)
    assert load_bundle(ensemble_dir).shares == (False, False)  # pressure first: IMU is not among its modalities
    groups = {k: obs[k] for k in ens.config.obs_groups}
    windows = ens.env_windows(obs)
    calls = []
    layer = ens.members[1].encoder.blocks[0]["pressure"]
    hook = layer.register_forward_hook(lambda *args: calls.append(1))
    try:
        shared = ens.correction(windows, groups)
    finally:
        hook.remove()
    assert not calls  # the second member's unimodal layers did not run
    ens.shares = (False, False)
    assert np.array_equal(shared, ens.correction(windows, groups))
    # a member whose encoder weights differ runs its own pass
    other = load_bundle(out)
    with torch.no_grad():
        next(other.members[1].encoder.blocks[0]["pressure"].parameters()).add_(1e-3)
    assert not shares_unimodal(other.members[0], other.members[1])
    assert shares_unimodal(ens.members[0], ens.members[1]) and not shares_unimodal(ens.members[1], ens.members[0])
    # missing or non-finite touch in the shared pass: TouchUnavailable, as in the members' own passes
    ens.shares = (False, True)
    _refuses_missing_imu_and_non_finite_touch(ens, windows, groups, "imu", np.inf)
    # deploy's traced shared pass (prepare_realtime): the same numbers, traced once per input shape, and the same
    # refusals (a trace keeps no Python checks: the finite check runs before it)
    eager = ens.correction(windows, groups)
    ens.prepare_realtime()
    assert ens.traced_shared == {}
    np.testing.assert_allclose(ens.correction(windows, groups), eager, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ens.correction(windows, groups), eager, rtol=0, atol=1e-6)
    assert len(ens.traced_shared) == 1
    _refuses_missing_imu_and_non_finite_touch(ens, windows, groups, "imu", np.inf)


def test_bad_per_dimension_weights_are_refused(ensemble_dir, tmp_path, capsys):
    member = str(ensemble_dir / "members" / "pressure")
    cases = [
        (["--dim-weights", "1", "1", "1"], "not the same count for each of the 2 members"),
        (["--dim-weights", *["-1"] * 8, *["1"] * 8], "numbers in [0, 10]"),
        (["--dim-weights", *["0"] * 8, *["1"] * 8], "are all 0"),
        (["--dim-weights", *["1"] * 6], "3 dim_weights for a 8-dimensional latent"),
    ]
    for extra, message in cases:
        assert main(["ensemble-adapters", "--members", member, member, *extra, "--out", str(tmp_path / "e")]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
        assert not (tmp_path / "e" / "config.json").exists()
    # the same checks when a hand-written config.json is loaded
    path = tmp_path / "hand"
    shutil.copytree(ensemble_dir / "members", path / "members")
    for dims, message in (([1.0] * 7, "7 dim_weights for a 8-dimensional latent"), ([float("nan")] * 8, "numbers in"),
                          ([True] * 8, "numbers in")):
        (path / "config.json").write_text(json.dumps({"kind": "adapter-ensemble", "format_version": 1, "members": [
            {"adapter": "members/pressure", "weight": 1.0, "dim_weights": dims}]}))
        with pytest.raises(BundleError, match=message):
            load_bundle(path)


def test_missing_or_non_finite_touch_is_touch_unavailable(ensemble_dir, env_obs):
    env, obs = env_obs
    ens = load_ensemble(ensemble_dir)
    groups = {k: obs[k] for k in ens.config.obs_groups}
    windows = ens.env_windows(obs)
    _refuses_missing_imu_and_non_finite_touch(ens, windows, groups, "pressure", np.nan)


def _refuses_missing_imu_and_non_finite_touch(ens, windows, groups, bad_window, bad_value):
    no_imu = {f: {"pressure": w["pressure"]} for f, w in windows.items()}
    with pytest.raises(TouchUnavailable, match="imu"):
        ens.correction(no_imu, groups)
    bad = {f: dict(w) for f, w in windows.items()}
    bad["ring"][bad_window] = np.full_like(bad["ring"][bad_window], bad_value)
    with pytest.raises(TouchUnavailable, match="non-finite"):
        ens.correction(bad, groups)


def test_bad_ensembles_are_refused_with_the_reason(ensemble_dir, tmp_path):
    def write(name, data):
        path = tmp_path / name
        shutil.copytree(ensemble_dir / "members", path / "members")
        (path / "config.json").write_text(json.dumps({"kind": "adapter-ensemble", "format_version": 1, **data}))
        return path

    with pytest.raises(BundleError, match="at least one member"):
        load_bundle(write("empty", {"members": []}))
    for name, weight in (("nan", float("nan")), ("negative", -0.5), ("text", "0.5")):
        with pytest.raises(BundleError, match=r"weights must be numbers in \(0, 10\]"):
            load_bundle(write(name, {"members": [{"adapter": "members/pressure", "weight": weight}]}))
    with pytest.raises(BundleError, match="member 'members/gone'"):
        load_bundle(write("gone", {"members": [{"adapter": "members/gone", "weight": 1.0}]}))
    with pytest.raises(BundleError, match="touch_every"):
        load_bundle(write("every", {"members": [{"adapter": "members/pressure", "weight": 1.0}], "touch_every": 0}))
    for name, smoothing in (("smooth_one", 1.0), ("smooth_negative", -0.1), ("smooth_text", "0.5")):
        with pytest.raises(BundleError, match=r"touch_smoothing must be a number in \[0, 1\)"):
            load_bundle(write(name, {"members": [{"adapter": "members/pressure", "weight": 1.0}],
                                     "touch_smoothing": smoothing}))
    with pytest.raises(BundleError, match="unknown config keys"):
        load_bundle(write("typo", {"members": [{"adapter": "members/pressure", "wieght": 1.0}]}))
    # a member whose student changed since it was trained is refused as the adapter alone would be
    stale = write("stale", {"members": [{"adapter": "members/pressure", "weight": 1.0}]})
    cfg_path = stale / "members" / "pressure" / "config.json"
    cfg = json.loads(cfg_path.read_text())
    cfg["student_sha256"] = "0" * 16
    cfg_path.write_text(json.dumps(cfg))
    with pytest.raises(BundleError, match="member 'members/pressure'.*retrain the adapter"):
        load_bundle(stale)


def test_evaluate_with_an_ensemble(ensemble_dir, tmp_path):
    cfg = job.Config(policies={"student": "student", "ensemble": str(ensemble_dir)}, episodes=2, episode_steps=8,
                     out=tmp_path / "eval", num_envs=2, nthread=1, progress=False, seed=100)
    rows = job.run(cfg)
    assert [r["policy"] for r in rows] == ["student", "ensemble"]
    digest = weights_digest(str(ensemble_dir))
    member = ensemble_dir / "members" / "pressure" / "adapter.safetensors"
    original = member.read_bytes()
    try:
        member.write_bytes(original[:-4] + b"\x00\x00\x00\x00")  # a member retrained in place changes the identity
        assert weights_digest(str(ensemble_dir)) != digest
    finally:
        member.write_bytes(original)


def test_latent_errors_of_an_ensemble(ensemble_dir, load_script, tmp_path):
    """experiments/tools/adapter_latent_errors.py reads an ensemble as it reads one adapter: its latent is the shared
    student's plus the weighted correction. (+0.1 kg: a condition of every hand's suite; the hardware physics' cups
    reach 0.4 kg, which leaves no room for +0.2 kg under MAX_OBJECT_MASS.)"""
    out = tmp_path / "errors"
    args = ["--adapter", str(ensemble_dir), "--condition", "mass_+0.1kg", "--num-envs", "2", "--steps", "6",
            "--seed", "5", "--out", str(out)]
    assert load_script("adapter_latent_errors").main(args) == 0
    total = json.loads((out / "errors.json").read_text())["total"]
    assert total["samples"] == 2 * 2  # 2 envs x refreshes at steps 0 and 3
    assert total["mse_adapted"] != total["mse_student"]  # the members' corrections moved the latent


def test_ensemble_adapters_refuses_bad_input_with_one_line(ensemble_dir, tmp_path, capsys):
    """Bad input ends with one line and status 2, nothing written; an existing bundle is never overwritten (a
    request that cannot be done: status 1)."""
    member = str(ensemble_dir / "members" / "pressure")
    cases = [
        (["--members", member, "--weights", "1", "2"], "2 weights for 1 members", 2),
        (["--members", str(tmp_path / "nothing")], "not an adapter bundle", 2),
        (["--members", str(ensemble_dir)], "an adapter ensemble, not one adapter; name one of its members", 2),
        (["--members", member, "--out", str(ensemble_dir)], "already holds a bundle", 1),
    ]
    for args, message, status in cases:
        out = [] if "--out" in args else ["--out", str(tmp_path / "e")]
        assert main(["ensemble-adapters", *args, *out]) == status
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
    assert not (tmp_path / "e" / "config.json").exists()
    # referenced where they are (--no-copy), with the default weights 1/K
    assert main(["ensemble-adapters", "--members", member, member, "--no-copy", "--out", str(tmp_path / "ref")]) == 0
    cfg = json.loads((tmp_path / "ref" / "config.json").read_text())
    assert [m["weight"] for m in cfg["members"]] == [0.5, 0.5] and cfg["touch_every"] == 4
    assert cfg["touch_smoothing"] == 0.0
    assert not (tmp_path / "ref" / "members").exists()
    # smoothing over refreshes: recorded in the bundle and read back; out of [0, 1) refused with one line
    assert main(["ensemble-adapters", "--members", member, "--touch-smoothing", "0.75", "--out",
                 str(tmp_path / "smooth")]) == 0
    assert load_bundle(tmp_path / "smooth").touch_smoothing == 0.75
    assert main(["ensemble-adapters", "--members", member, "--touch-smoothing", "1", "--out",
                 str(tmp_path / "never")]) == 2
    err = capsys.readouterr().err
    assert "touch_smoothing must be a number in [0, 1)" in err and "Traceback" not in err
    assert not (tmp_path / "never" / "config.json").exists()


def test_bench_adapter_times_an_ensemble(ensemble_dir, load_script, capsys):
    bench = load_script("bench_adapter")
    assert bench.main(["--adapter", str(ensemble_dir), "--iters", "1", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    result = json.loads(out.strip().splitlines()[-1])
    assert "touch step, pressure+imu" in out and result["step_ms"] > result["student_ms"] > 0
    assert result["touch_every"] == 3
    assert bench.main(["--adapter", "student", "--iters", "1"]) == 2  # reads no touch: one line, no traceback
    assert "not a tactile adapter" in capsys.readouterr().err
