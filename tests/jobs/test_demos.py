"""`rotate demos --task insertion`: the expert's demonstrations as sessions (camera, proprioception, actions,
touch, privileged labels), the touch history there from the first action, deterministic and resumable."""

from __future__ import annotations

import numpy as np

from rotation.cli import main
from rotation.data.dataset import TouchWindows, find_sessions
from rotation.data.session_reader import SessionReader
from rotation.jobs import demos


def test_demonstrations_are_sessions_a_policy_can_learn_from(tmp_path, capsys):
    out = tmp_path / "demos"
    cfg = demos.Config(episodes=2, out=out, seed=5, image_size=(48, 36), progress=False)
    assert demos.run(cfg)["episodes"] == 2
    paths = find_sessions(out)
    assert len(paths) == 2
    for path in paths:
        with SessionReader(path) as r:
            steps = r.meta.properties["steps"]
            assert r.meta.properties["success"] is True and steps >= 5
            for name in ("camera/wrist", "joints/position", "wrist/pose", "actions/wrist", "labels/depth"):
                assert len(r.stream(name, lazy=True)) == steps, name
            assert r.stream("camera/wrist", lazy=True).data.shape[1:] == (36, 48, 3)
            t_first = r.stream("actions/wrist").timestamps[0]
            assert t_first >= 1.12  # the touch window of the first action has its history
            depth = r.stream("labels/depth").data[:, 0]
            assert depth[0] < 0 and depth[-1] > 0.01  # from below the socket to seated
    windows = TouchWindows(paths, labels=("depth",))
    assert min(float(windows[i]["time"]) for i in range(0, len(windows), 50)) <= 1.2 + 1e-6
    with SessionReader(paths[0]) as r:
        first = r.stream("actions/wrist").data.copy()
    # the same command again: nothing left to record; another run with the same seed records the same actions
    assert demos.run(cfg)["episodes"] == 0
    again = tmp_path / "again"
    demos.run(demos.Config(episodes=1, out=again, seed=5, image_size=(48, 36), progress=False))
    with SessionReader(find_sessions(again)[0]) as r:
        assert np.array_equal(r.stream("actions/wrist").data, first)
    assert main(["demos", "--episodes", "0", "--out", str(tmp_path / "x")]) == 2
    assert "episodes" in capsys.readouterr().err


def test_another_runs_demonstration_is_refused_not_overwritten(tmp_path, capsys):
    out = tmp_path / "demos"
    demos.run(demos.Config(episodes=1, out=out, seed=5, image_size=(48, 36), progress=False))
    path = find_sessions(out)[0]
    before = path.read_bytes()
    assert main(["demos", "--episodes", "1", "--out", str(out), "--seed", "6", "--image-size", "48", "36"]) == 1
    assert "another run's demonstration" in capsys.readouterr().err
    assert path.read_bytes() == before


def test_the_closed_loop_touch_is_the_touch_the_demonstrations_hold(tmp_path):
    """A policy acting in the env reads touch windows rendered from the live contact history; they equal the windows
    the loader renders from the recorded demonstration of the same episode."""
    from envs.grasp_cache import load_default_cache
    from envs.insertion import InsertionConfig, InsertionSim, draw_episode
    from envs.insertion_expert import InsertionExpert
    from envs.sensors.digit360_image import pack_image

    out = tmp_path / "demos"
    demos.run(demos.Config(episodes=1, out=out, seed=7, image_size=(48, 36), progress=False))
    recorded = TouchWindows(find_sessions(out))
    cfg = InsertionConfig(image_size=(48, 36))
    grasps = load_default_cache("cup", "", "digit360_v4")
    seed = 7 * 1_000_000
    sim = InsertionSim(cfg, draw_episode(cfg, seed, grasps), grasps)
    expert = InsertionExpert(cfg, seed)
    obs, info = sim.reset(), {}
    for _ in range(6):
        obs, _, info = sim.step(expert.act(obs, info))
    live = sim.touch.windows(("index", "thumb"))
    frame_time = float(np.floor(sim.touch.times[-1] * 30 + 1e-6) / 30)
    times = np.array([float(recorded[i]["time"]) for i in range(len(recorded))])
    for finger, f in (("index", 0), ("thumb", 3)):
        i = next(i for i in np.flatnonzero(np.isclose(times, frame_time)) if int(recorded[i]["finger"]) == f)
        sample = recorded[int(i)]
        assert np.allclose(sample["imu"].numpy(), live[finger]["imu"], atol=1e-6)
        assert np.allclose(sample["pressure"].numpy()[:, 0], live[finger]["pressure"], atol=1e-4)
        assert np.allclose(sample["image"].numpy(), pack_image(live[finger]["image"]), atol=1e-6)


def test_noisy_demonstrations_record_the_experts_corrections_not_the_noise(tmp_path, capsys):
    """With executed-action noise (DART) the recorded action is what the expert chose on the state the noise led to:
    the wrist's recorded offsets are not the sum of the recorded actions, the same command records the same file, and
    a clean run's folder refuses a noisy run."""
    clean, noisy = tmp_path / "clean", tmp_path / "noisy"
    demos.run(demos.Config(episodes=1, out=clean, seed=5, image_size=(48, 36), progress=False))
    cfg = demos.Config(episodes=1, out=noisy, seed=5, image_size=(48, 36), noise_m=0.0004, noise_rad=0.003,
                       progress=False)
    demos.run(cfg)

    def read(out):
        with SessionReader(find_sessions(out)[0]) as r:
            return (r.meta.properties, r.stream("actions/wrist").data.copy(), r.stream("wrist/pose").data.copy(),
                    r.meta.extra["demos"])

    props_c, act_c, pose_c, _ = read(clean)
    props_n, act_n, pose_n, extra = read(noisy)
    assert (extra["noise_m"], extra["noise_rad"]) == (0.0004, 0.003) and props_n["steps"] == len(act_n)
    n = min(len(act_c), len(act_n))
    assert not np.allclose(act_c[:n], act_n[:n])  # the expert reacted to other states
    # clean: each action moves the wrist target by itself (within the env's clip); noisy: by itself plus the noise
    step_c = np.diff(pose_c[:, :3], axis=0) - np.clip(act_c[:-1, :3], -0.003, 0.003)
    step_n = np.diff(pose_n[:, :3], axis=0) - np.clip(act_n[:-1, :3], -0.003, 0.003)
    assert np.abs(step_c).max() < 1e-6 and 2e-4 < step_n.std() < 6e-4
    again = tmp_path / "again"
    demos.run(demos.Config(**{**cfg.__dict__, "out": again}))
    assert np.array_equal(read(again)[1], act_n)
    assert main(["demos", "--episodes", "1", "--out", str(clean), "--seed", "5", "--image-size", "48", "36",
                 "--noise-m", "0.0004"]) == 1
    assert "another run's demonstration" in capsys.readouterr().err
    assert main(["demos", "--noise-m", "0.01", "--out", str(tmp_path / "x")]) == 2
    # the expert's way of finding the hole is part of the run: feel by default, recorded, a state run refused here
    assert extra["expert_align"] == "feel" and {"lost", "retries"} <= set(props_n)
    assert main(["demos", "--episodes", "1", "--out", str(clean), "--seed", "5", "--image-size", "48", "36",
                 "--expert-align", "state"]) == 1
    assert "another run's demonstration" in capsys.readouterr().err
    # so is the plug's grip: in the fingertips by default, the grasp row it was held at recorded, a palm run refused
    assert extra["grip"] == "fingertips" and {"grasp_u", "regrips"} <= set(props_n)
    assert main(["demos", "--episodes", "1", "--out", str(clean), "--seed", "5", "--image-size", "48", "36",
                 "--grip", "palm"]) == 1
    assert "another run's demonstration" in capsys.readouterr().err
    # and the wrist: stiff by default, recorded, a compliant run refused here
    assert extra["wrist"] == "stiff"
    assert main(["demos", "--episodes", "1", "--out", str(clean), "--seed", "5", "--image-size", "48", "36",
                 "--wrist", "compliant"]) == 1
    assert "another run's demonstration" in capsys.readouterr().err
