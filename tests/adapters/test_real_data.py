"""The real-data path of `rotate finetune-adapter`: sessions recorded by `rotate deploy` on the emulated hand (with
emulated Digit 360 fingertips and stated object properties) become adapter training samples; the rebuilt
observations are the ones the deploy loop fed the policy; training on them writes a loadable adapter that lowers
the latent error; bad sessions are refused before anything is written."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
import torch
from deploy_checks import load_fault

from adapters.bundle import load_adapter
from adapters.finetune import job as finetune
from adapters.real_data import priv_vectors, proprio_observations, session_samples, start_positions
from adapters.session_checks import check_session, check_sessions
from envs import constants as C
from rotation.bundles import load_bundle
from rotation.data.properties import parse_properties
from rotation.data.session import SessionError, SessionMeta, StreamSetup
from rotation.data.session_reader import SessionReader
from rotation.data.session_writer import SessionWriter
from rotation.deploy import job as deploy_job
from rotation.deploy import loop as deploy_loop
from rotation.deploy.policy import PolicyState
from rotation.hardware.digit360 import window as dw

FINGERS = C.FINGERS
PROPERTIES = ("mass=0.1,friction=0.9,com=0,0,0.005,scale=0.78", "mass=0.2,friction=0.5,com=0,0.002,0,scale=0.8")


class _SpyState(PolicyState):
    """The deploy loop's PolicyState, remembering the observation it handed out after each number of pushes (step k
    of the loop hands out the observation after k pushes)."""

    seen: dict[int, dict[str, np.ndarray]] = {}

    def push(self, q):
        super().push(q)
        self.pushes = getattr(self, "pushes", 0) + 1

    def observation(self):
        obs = super().observation()
        _SpyState.seen[getattr(self, "pushes", 0)] = {k: v.copy() for k, v in obs.items()}
        return obs


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """Two 3 s sessions of the shipped student on the emulated Allegro with emulated fingertips and stated
    properties; the first with the observations its loop fed the policy."""
    root = tmp_path_factory.mktemp("sessions")
    seen = {}
    for i, props in enumerate(PROPERTIES):
        # a loaded 2-core machine may end a run in a load fault (deploy_checks): its session is kept aside (in
        # attempts/) and the cup recorded again, up to three times, so that the tests read whole sessions
        for attempt in range(3):
            _SpyState.seen = {}
            path = root / "attempts" / f"s{i}_{attempt}.h5"
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(deploy_loop, "PolicyState", _SpyState)
                summary = deploy_job.run(deploy_job.Config(hand="sim-allegro", policy="student", duration=3.0,
                                                           record=str(path), digit360="sim", grasp=i,
                                                           properties=props, status_every_s=10.0))
            if summary["fault"] is None:
                break
            assert load_fault(summary), summary["fault"]
        assert summary["fault"] is None, summary["fault"]
        path.rename(root / f"s{i}.h5")
        if i == 0:
            seen = dict(_SpyState.seen)
    return root, seen


def test_rebuilt_observations_are_what_the_deploy_loop_fed_the_policy(sessions):
    root, seen = sessions
    with SessionReader(root / "s0.h5") as r:
        q, targets = r.stream("joints/position").data, r.stream("joints/target").data
    steps = np.array([0, 5, C.HISTORY_STEPS, C.HISTORY_STEPS + 7, len(q) - 1])
    obs = proprio_observations(q, targets, steps)
    for j, k in enumerate(steps):
        fed = seen[int(k)]
        for group in ("proprio", "proprio_hist"):
            assert obs[group][j].shape == fed[group].shape and obs[group][j].dtype == np.float32
        # the frames pushed by the loop: equal up to the float32 recording of the joints
        pushed = min(int(k), C.HISTORY_STEPS)
        tail = slice(C.HISTORY_STEPS - pushed, None)
        np.testing.assert_allclose(obs["proprio_hist"][j][tail], fed["proprio_hist"][tail], rtol=0, atol=2e-6)
        if k >= C.PROPRIO_STEPS:
            np.testing.assert_allclose(obs["proprio"][j], fed["proprio"], rtol=0, atol=2e-6)
        # the start fill: the first recorded pose stands in for the one the loop read before its warm-up, while the
        # hand held its start pose (settling by a few mrad at most)
        np.testing.assert_allclose(obs["proprio_hist"][j], fed["proprio_hist"], rtol=0, atol=2e-2)


def test_samples_of_a_recorded_session(sessions):
    root, _ = sessions
    encoder = load_bundle("teacher").net.extractor.encoder
    student = load_bundle("student")

    def phi(obs):
        return student.net.extractor.z(student._tensors(obs, batched=True)).detach()

    def samples(position):
        info = check_session(root / "s0.h5", FINGERS, ("pressure",), 20.0, position)
        return info, session_samples(info, encoder, phi, FINGERS, ("pressure",), every=2, position=position)

    info, s = samples("fit")
    assert info.properties == parse_properties(PROPERTIES[0]) and info.hand == "allegro"
    assert 10 <= len(s) <= 30 and np.all(s.steps % 2 == 0) and s.skipped > 0  # the first ~1.1 s have no window
    for f in FINGERS:
        assert s.windows[f]["pressure"].shape == (len(s), dw.SERIES_LEN, 1)
        assert np.all(np.isfinite(s.windows[f]["pressure"]))
    assert s.obs["proprio_hist"].shape == (len(s), C.HISTORY_STEPS, C.PROPRIO_DIM)
    np.testing.assert_allclose(s.z_student, phi(s.obs).numpy(), rtol=1e-6, atol=1e-6)
    # the window a deployed reader would make at a sampled step, from the recorded samples up to then
    with SessionReader(root / "s0.h5") as r:
        p = r.stream("digit360/thumb/pressure")
        imu = r.stream("digit360/thumb/imu")
        t = s.times[3]
        t_end = min(p.timestamps[p.timestamps <= t][-1], imu.timestamps[imu.timestamps <= t][-1])
        want = dw.series_from_samples(p.timestamps, p.data, t_end, dw.PRESSURE_RATE)
    np.testing.assert_array_equal(s.windows["thumb"]["pressure"][3], want)

    # targets: the teacher's z of the stated properties at a stand-in position
    props = parse_properties(PROPERTIES[0])
    with torch.no_grad():
        z = encoder(torch.as_tensor(priv_vectors(props, s.positions), dtype=torch.float32)).numpy()
    np.testing.assert_allclose(s.z, z, rtol=1e-6, atol=1e-6)
    _, avg = samples("average")
    with torch.no_grad():
        z = encoder(torch.as_tensor(priv_vectors(props, start_positions(0.78)), dtype=torch.float32)).mean(0)
    np.testing.assert_allclose(avg.z, np.broadcast_to(z.numpy(), avg.z.shape), rtol=1e-6, atol=1e-6)
    # the emulated hand records the object's pose: fitting the position to the student's latent lands nearer the
    # target at the true position than the average over start positions does
    _, rec = samples("recorded")
    assert np.array_equal(rec.steps, s.steps) and avg.positions is None
    fit_err, avg_err = ((s.z - rec.z) ** 2).mean(), ((avg.z - rec.z) ** 2).mean()
    assert fit_err < avg_err, (fit_err, avg_err)
    assert np.abs(s.positions - rec.positions).max() < 0.05


def _tiny(out, root, **kw) -> finetune.Config:
    base = dict(out=out, sessions=(root,), modalities="pressure", epochs=12, batch_size=8, lr=2e-3, hidden=(64,),
                sample_every=2, val_fraction=0.5, progress=False, torch_threads=1, seed=0)
    return finetune.Config(**{**base, **kw})


def test_finetune_on_sessions_writes_an_adapter_that_lowers_the_latent_error(sessions, tmp_path):
    root, _ = sessions
    out = tmp_path / "run"
    result = finetune.run(_tiny(out, root))
    hist = result.history
    assert [h["epoch"] for h in hist] == list(range(13))
    assert hist[0]["latent_mse"] == pytest.approx(hist[0]["student_mse"])  # epoch 0: exactly the student
    assert hist[-1]["latent_mse"] < 0.5 * hist[-1]["student_mse"], hist[-1]
    assert "val_latent_mse" in hist[-1] and hist[-1]["val_student_mse"] > 0
    assert hist[0]["action_mse"] == pytest.approx(hist[0]["student_action_mse"])  # the actions too
    assert hist[-1]["action_mse"] < hist[-1]["student_action_mse"] and "val_action_mse" in hist[-1]
    rows = [json.loads(line) for line in (out / "curves.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [h["epoch"] for h in hist]
    assert (out / "config.json").is_file() and any((out / "tb").iterdir())
    policy = load_adapter(result.bundle_dir)
    card = policy.adapter_config.card
    assert policy.adapter_config.modalities == ("pressure",) and card["epochs"] == 12 and card["samples"] > 0
    assert len(card["sessions"]) == 1 and len(card["val_sessions"]) == 1
    assert any(p.abs().sum() > 0 for p in policy.adapter.zero.parameters())

    # exact resume: 5 epochs, then on to 12, equals 12 straight
    part = tmp_path / "part"
    finetune.run(_tiny(part, root, epochs=5))
    resumed = finetune.run(_tiny(part, root, epochs=12, resume=True))
    a, b = policy.adapter.state_dict(), load_adapter(resumed.bundle_dir).adapter.state_dict()
    for name, x in a.items():
        assert torch.equal(x, b[name]), name


def _copy(src, dst, **attrs):
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        for key, value in attrs.items():
            f.attrs[key] = value
    return dst


def test_bad_sessions_are_refused_before_training(sessions, tmp_path):
    root, _ = sessions
    src = root / "s0.h5"
    no_props = _copy(src, tmp_path / "no_props.h5", properties=json.dumps({"scale": 0.78, "grasp": 0}))
    with pytest.raises(SessionError, match=r"no_props\.h5.*missing measured object properties mass, friction, com"):
        check_session(no_props, FINGERS, ("pressure",), 20.0)
    bad = _copy(src, tmp_path / "grams.h5", properties=json.dumps({"scale": 0.78, "mass": 120, "friction": 0.8,
                                                                    "com": [0, 0, 0]}))
    with pytest.raises(SessionError, match=r"grams\.h5.*'mass' = 120"):
        check_session(bad, FINGERS, ("pressure",), 20.0)
    with pytest.raises(SessionError, match="at 20 Hz, the student acts at 30 Hz"):
        check_session(src, FINGERS, ("pressure",), 30.0)
    leap = _copy(src, tmp_path / "leap.h5", hand="leap")
    with pytest.raises(SessionError, match=r"leap\.h5 comes from another hand \(leap, sim\)"):
        check_sessions([src, leap], FINGERS, ("pressure",), 20.0)
    xela = _copy(src, tmp_path / "xela.h5", hand="xela")
    with pytest.raises(SessionError, match=r"xela\.h5: recorded on the hand 'xela'"):
        check_session(xela, FINGERS, ("pressure",), 20.0)
    # joints only, no fingertips: named, with how to record them
    joints_only = tmp_path / "joints.h5"
    meta = SessionMeta(source="real", object="cup", control_hz=20.0, properties=parse_properties(PROPERTIES[0]))
    with SessionWriter(joints_only, meta, [StreamSetup(n, rate_hz=20.0) for n in ("joints/position",
                                                                                  "joints/target")]) as w:
        for k in range(5):
            w.append("joints/position", np.zeros((1, 16)), [k / 20])
            w.append("joints/target", np.zeros((1, 16)), [k / 20])
    with pytest.raises(SessionError, match=r"joints\.h5: missing stream\(s\) digit360/index/pressure.*--digit360"):
        check_session(joints_only, FINGERS, ("pressure",), 20.0)
    # through the job: refused before anything is written in --out
    out = tmp_path / "out"
    (tmp_path / "mixed").mkdir()
    shutil.copy(src, tmp_path / "mixed" / "a.h5")
    shutil.copy(no_props, tmp_path / "mixed" / "b.h5")
    with pytest.raises(SessionError, match=r"b\.h5.*missing measured object propert"):
        finetune.run(_tiny(out, tmp_path / "mixed"))
    assert not out.exists()
    with pytest.raises(SessionError, match=r"missing stream\(s\) digit360/index/image.*--record-media"):
        finetune.run(_tiny(out, root, modalities="img,pressure"))  # an emulated sensor records no frames
    with pytest.raises(ValueError, match="no session file or directory at"):
        finetune.run(_tiny(out, tmp_path / "nothing_here"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"sessions: no \.h5 session files under"):
        finetune.run(_tiny(out, tmp_path / "empty"))
    assert not out.exists()


def test_deploy_properties_option():
    assert parse_properties("mass=0.12,friction=0.8,com=0,0,0.01,scale=0.8") == {
        "mass": 0.12, "friction": 0.8, "com": [0.0, 0.0, 0.01], "scale": 0.8}
    assert parse_properties("") == {}
    for spec, match in [("weight=1", "unknown property 'weight'"), ("mass=abc", "'mass' = 'abc' is not a number"),
                        ("com=0,0", "'com' must be 3 numbers"), ("mass=120", r"'mass' = 120.0 is outside \(0, 2\]"),
                        ("mass=0.1,mass=0.2", "'mass' given twice"), ("0.1", "cannot read"),
                        ("friction=-1", "outside")]:
        with pytest.raises(ValueError, match=match):
            parse_properties(spec)
    with pytest.raises(ValueError, match="properties: .*--record"):
        deploy_job.Config(hand="sim-allegro", policy="student", properties="mass=0.1")
    with pytest.raises(ValueError, match="unknown property"):
        deploy_job.Config(hand="sim-allegro", policy="student", properties="mas=0.1", record="x.h5")


def test_finetune_on_sessions_with_joint_tracking_normalizes_by_the_training_samples(sessions, tmp_path):
    """--tracking on recorded sessions: the features come from the rebuilt history, their normalization from the
    training samples (the sessions' own joints), and the adapter learns from them."""
    from adapters.model import TRACKING_DIM

    root, _ = sessions
    result = finetune.run(_tiny(tmp_path / "run", root, epochs=4, tracking=True))
    adapter = load_adapter(result.bundle_dir).adapter
    assert adapter.cfg.tracking
    assert not torch.equal(adapter.track_std, torch.ones(TRACKING_DIM))
    assert 0.0 < float(adapter.track_std[:16].median()) < 0.2  # tracking errors in rad, not the defaults
    assert float(adapter.g[0].weight[:, -TRACKING_DIM:].detach().abs().sum()) > 0
    assert result.history[-1]["latent_mse"] < result.history[0]["latent_mse"]


def test_measured_properties_are_checked_against_the_shipped_teachers_ranges():
    """A lab's cup is warned about against the randomization the shipped teacher trained on (its card: the hand's
    own, with slippery cup surfaces down to x0.15 and cups to 0.5 kg), not Hora's nor the hand's default."""
    from adapters.session_checks import outside_training_ranges, teacher_randomization
    from envs.config import default_randomization

    rc = teacher_randomization()
    assert rc.surface_friction == (0.15, 1.0) and rc.mass == (0.02, 0.5)
    mug = {"scale": 1.0, "mass": 0.45, "friction": 0.2, "com": [0.0, 0.0, 0.0]}  # a slippery heavy mug it trained on
    assert outside_training_ranges(mug) == []
    notes = outside_training_ranges({**mug, "friction": 2.0, "mass": 0.55})
    assert notes == ["mass 0.55 (0.02..0.5)", "friction 2.0 (0.06..1.2)"]
    # against the hand's default randomization (what a teacher trained without the slippery cups knows)
    assert outside_training_ranges(mug, default_randomization()) == ["mass 0.45 (0.02..0.4)", "friction 0.2 (0.4..1.2)"]


def test_a_teacher_card_that_does_not_load_is_said_not_silently_replaced(tmp_path, caplog):
    """A card whose training config cannot be read back is reported before the default ranges are used; a bundle
    with no training config at all (from before cards kept it) takes the default quietly."""
    import json
    import logging
    import shutil

    from adapters.session_checks import teacher_randomization
    from envs.config import default_randomization
    from rotation.policy.bundle import resolve_bundle

    bundle = tmp_path / "teacher"
    shutil.copytree(resolve_bundle("teacher"), bundle)
    meta = json.loads((bundle / "config.json").read_text())
    meta["card"]["train_config"]["resume"] = "None"  # what the cards wrote before to_jsonable: not a path that loads
    meta["card"]["train_config"]["mass"] = "heavy"
    (bundle / "config.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING, logger="adapters.session_checks"):
        assert teacher_randomization(bundle) == default_randomization()
    assert "does not load" in caplog.text
    caplog.clear()
    del meta["card"]["train_config"]
    (bundle / "config.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING, logger="adapters.session_checks"):
        assert teacher_randomization(bundle) == default_randomization()
    assert caplog.text == ""


def test_a_teacher_card_naming_the_training_machines_files_still_gives_its_ranges(tmp_path, caplog):
    """A card records where its run started from and wrote to (--init-from, --resume, --out, a grasp cache): files of
    the machine that trained it, absent from a clone. The randomization is read all the same, and nothing is warned."""
    import json
    import logging
    import shutil

    from adapters.session_checks import teacher_randomization
    from rotation.policy.bundle import resolve_bundle

    bundle = tmp_path / "teacher"
    shutil.copytree(resolve_bundle("teacher"), bundle)
    meta = json.loads((bundle / "config.json").read_text())
    gone = tmp_path / "gone"
    meta["card"]["train_config"].update(init_from=str(gone / "bundle"), resume=str(gone / "last.zip"),
                                        out=str(tmp_path / "file"), grasp_cache=str(gone / "grasps.npz"),
                                        friction=[0.5, 1.1], mass=[0.03, 0.45])
    (tmp_path / "file").write_text("not a directory")
    (bundle / "config.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING, logger="adapters.session_checks"):
        rc = teacher_randomization(bundle)
    surface = tuple(meta["card"]["train_config"]["surface_friction"])  # the shipped teacher's own
    assert (rc.friction, rc.mass, rc.surface_friction) == ((0.5, 1.1), (0.03, 0.45), surface)
    assert caplog.text == ""
