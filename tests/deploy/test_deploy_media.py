"""A real Digit 360's camera and microphones in deploy: opened by its reader (OpenCV, sounddevice) when the policy
reads the image or the audio, recorded beside the serial streams, and refused before the start when they are not
there or their libraries are missing (how they are found on the sensor's USB hub: test_digit360_discovery.py).

OpenCV and sounddevice are stand-ins that deliver frames and 48 kHz int16 blocks from their own threads at the real
rates, as the libraries do. The serial streams are the Digit 360 emulator's.
"""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
import types
from pathlib import Path

import numpy as np
import pytest
from deploy_checks import again_if_loaded, assert_done_or_load_fault

from adapters.bundle import build_adapted
from rotation.cli import main
from rotation.deploy.sensors import check_media_extras, open_digit360
from rotation.hardware.digit360 import discovery
from rotation.hardware.digit360.discovery import Digit360Devices
from rotation.hardware.digit360.reader import SensorStale
from rotation.hardware.digit360.window import IMAGE_GAP, PRESSURE_RATE, SERIES_LEN, WindowNotReady
from rotation.sim_hardware.digit360_emulator import Digit360Emulator

ENCODER = "sparshx-tinier-sim"
FINGERS = ("index", "middle", "ring", "thumb")


# ------------------------------------------------------------------------------------------ library stand-ins
class Microphones:
    """sounddevice stand-in: each ``InputStream`` calls back from its own thread with 10 ms blocks of 2-channel
    int16 audio at 48 kHz (channel 0 counts samples modulo 20,000 from -10,000, channel 1 is its negative)."""

    block = 480

    def __init__(self, fail: tuple[str, ...] = ()) -> None:
        self.opened: list[dict] = []
        self.fail = fail
        self.module = types.ModuleType("sounddevice")
        self.module.InputStream = self.stream
        self.module.query_devices = self.query
        self.module.check_input_settings = lambda **settings: None

    def query(self, device, kind):
        if device in self.fail:
            raise ValueError(f"No {kind} device matching {device!r}")
        return {"name": f"Digit 360: USB Audio {device}", "max_input_channels": 2, "default_samplerate": 48000.0}

    def stream(self, *, samplerate, channels, dtype, device, callback):
        if device in self.fail:
            raise ValueError(f"No input device matching {device!r}")
        self.opened.append({"samplerate": samplerate, "channels": channels, "dtype": dtype, "device": device})
        return _Stream(callback, self.block)


class _Stream:
    def __init__(self, callback, block: int) -> None:
        self.callback, self.block = callback, block
        self.stopped = threading.Event()
        self.thread = threading.Thread(target=self._run, name="fake-portaudio", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        n, t0 = 0, time.monotonic()
        while not self.stopped.wait(max(0.0, t0 + (n + self.block) / 48_000 - time.monotonic())):
            ch0 = ((n + np.arange(self.block)) % 20_000 - 10_000).astype(np.int16)
            self.callback(np.stack([ch0, -ch0], axis=1), self.block, None, None)
            n += self.block

    def stop(self) -> None:
        self.stopped.set()
        self.thread.join()

    def close(self) -> None:
        pass


class Cameras:
    """OpenCV stand-in: ``VideoCapture(path, api)`` of a known path gives 1280 x 720 BGR frames at 30 fps (MJPG),
    frame k uniform (B, G, R) = (10, 20, k mod 256)."""

    def __init__(self, paths: tuple[str, ...]) -> None:
        self.paths, self.opened, self.captures = paths, [], []
        m = types.ModuleType("cv2")
        m.CAP_PROP_FRAME_WIDTH, m.CAP_PROP_FRAME_HEIGHT, m.INTER_AREA, m.COLOR_BGR2RGB = 3, 4, 3, 4
        m.CAP_PROP_FPS, m.CAP_PROP_FOURCC, m.CAP_ANY, m.CAP_V4L2 = 5, 6, 0, 200
        m.VideoCapture = self.capture
        m.resize = lambda img, size, interpolation=None: img[
            (np.arange(size[1]) * img.shape[0] // size[1])[:, None], np.arange(size[0]) * img.shape[1] // size[0]]
        m.cvtColor = lambda img, code: np.ascontiguousarray(img[..., ::-1])
        self.module = m

    def capture(self, path, api=0):
        self.opened.append(path)
        self.captures.append(_Capture(path in self.paths))
        return self.captures[-1]


class _Capture:
    def __init__(self, ok: bool) -> None:
        self.ok, self.k, self.t0 = ok, 0, time.monotonic()
        self.frozen = False  # True: every read fails, as from a camera that stopped

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return self.ok

    def open(self, path) -> bool:
        return self.ok

    def set(self, prop, value) -> bool:
        return True

    def get(self, prop) -> float:  # width, height, fps, FOURCC 'MJPG' (OpenCV's property numbers)
        return {3: 1280.0, 4: 720.0, 5: 30.0, 6: float(int.from_bytes(b"MJPG", "little"))}.get(prop, 0.0)

    def read(self):
        time.sleep(max(0.0, self.t0 + self.k / 30 - time.monotonic()))
        if self.frozen:
            time.sleep(0.05)
            return False, None
        frame = np.empty((720, 1280, 3), np.uint8)
        frame[...] = (10, 20, self.k % 256)
        self.k += 1
        return True, frame

    def release(self) -> None:
        self.ok = False


def ready_window(reader, timeout_s: float = 5.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return reader.window()
        except (WindowNotReady, SensorStale):  # no serial sample yet, or not enough history
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_a_real_sensors_reader_gives_its_camera_and_microphones(monkeypatch):
    mics, cams = Microphones(), Cameras(("/dev/video2",))
    monkeypatch.setitem(sys.modules, "sounddevice", mics.module)
    monkeypatch.setitem(sys.modules, "cv2", cams.module)
    with contextlib.ExitStack() as stack:
        emu = stack.enter_context(Digit360Emulator())
        readers = open_digit360({"index": emu.path}, stack,
                                media={"index": Digit360Devices("/dev/video2", "(hw:1,0)")})
        w = ready_window(readers["index"])
        cams.captures[0].frozen = True  # the camera stops: its last frames are not passed off as the present
        time.sleep(0.7)
        with pytest.raises(SensorStale, match="newest camera frame is .* s old"):
            readers["index"].window()
    assert mics.opened == [{"samplerate": 48_000, "channels": 2, "dtype": "int16", "device": "(hw:1,0)"}]
    assert cams.opened == ["/dev/video2"]
    assert w["image"].shape == (6, 224, 224) and w["audio"].shape == (2, 27_000)
    assert w["imu"].shape == (224, 3) and w["pressure"].shape == (224, 1)
    image = w["image"].astype(int)  # channel-major [R(t-5), R(t), G(t-5), G(t), B(t-5), B(t)]
    assert np.all((image[1] - image[0]) % 256 == 5) and np.all(image[2:4] == 20) and np.all(image[4:] == 10)
    audio = w["audio"].astype(int)  # 27,000 consecutive samples, the two microphones kept apart
    assert np.all((np.diff(audio[0]) + 20_000) % 20_000 == 1) and np.array_equal(audio[1], -audio[0])


def test_microphones_that_do_not_open_fail_the_sensor_without_a_leak(monkeypatch):
    from rotation.deploy.sensors import SensorError

    monkeypatch.setitem(sys.modules, "sounddevice", Microphones(fail=("(hw:9,0)",)).module)
    with contextlib.ExitStack() as stack:
        emu = stack.enter_context(Digit360Emulator())
        with pytest.raises(SensorError, match=r"digit360 thumb .*microphones '\(hw:9,0\)' did not open"):
            open_digit360({"thumb": emu.path}, stack, media={"thumb": Digit360Devices(None, "(hw:9,0)")})


def test_missing_libraries_are_named_before_the_start(monkeypatch):
    monkeypatch.setitem(sys.modules, "sounddevice", None)  # the import fails, as without the extra
    monkeypatch.setitem(sys.modules, "cv2", None)
    check_media_extras({})  # serial streams only: nothing to import
    both = {"index": Digit360Devices("/dev/video2", None), "thumb": Digit360Devices(None, "(hw:1,0)")}
    with pytest.raises(ValueError, match=r"needs cv2 \(.*\), sounddevice \(.*\): pip install 'tactile-rotation"):
        check_media_extras(both)


# ------------------------------------------------------------------------------------------ deploy, end to end
@pytest.fixture(scope="module")
def audio_adapter(tmp_path_factory, policy) -> str:
    """A fresh adapter on the audio and the pressure (zero correction: it acts as its student)."""
    path = tmp_path_factory.mktemp("adapter") / "audio_pressure"
    build_adapted(policy, ENCODER, ("mic", "pressure"), touch_every=4).save(path)
    return str(path)


def test_deploy_opens_each_named_sensors_microphones_for_an_audio_adapter(audio_adapter, capsys, hand_hook,
                                                                           monkeypatch):
    mics, cards = Microphones(), {}

    def deploy() -> dict:
        mics.opened.clear()
        with contextlib.ExitStack() as stack:
            emus = {f: stack.enter_context(Digit360Emulator()) for f in FINGERS}
            cards.clear()
            cards.update({emu.path: f"(hw:{i + 1},0)" for i, emu in enumerate(emus.values())})
            monkeypatch.setattr(discovery, "find_digit360_devices",
                                lambda port, sysfs="/sys": Digit360Devices(None, cards[port]))
            code = main(["deploy", "--hand", "sim-allegro", "--policy", audio_adapter, "--duration", "2.5",
                         "--digit360", ",".join(f"{f}={emu.path}" for f, emu in emus.items())])
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert code == summary["exit_code"]
        return summary

    monkeypatch.setitem(sys.modules, "sounddevice", mics.module)
    summary = again_if_loaded(deploy)
    assert sorted(m["device"] for m in mics.opened) == sorted(cards.values())
    assert_done_or_load_fault(summary)
    # the adapter read and encoded every fingertip's microphone window (whether a correction was still fresh enough
    # to act with is the machine's speed: a loaded one took 1.5 s per refresh)
    assert summary["touch"]["refreshes"] >= 1, summary["touch"]


def test_deploy_refuses_an_audio_adapter_when_no_microphones_are_found(audio_adapter, capsys, hand_hook):
    with contextlib.ExitStack() as stack:
        emus = {f: stack.enter_context(Digit360Emulator()) for f in FINGERS}
        code = main(["deploy", "--hand", "sim-allegro", "--policy", audio_adapter, "--duration", "1",
                     "--digit360", ",".join(f"{f}={emu.path}" for f, emu in emus.items())])
    err = capsys.readouterr().err
    assert code == 2 and "gives imu, pressure, not audio" in err and "USB hub" in err  # a pty has no hub
    code = main(["deploy", "--hand", "sim-allegro", "--policy", audio_adapter, "--duration", "1",
                 "--digit360", "D360-A,D360-B,D360-C,D360-NOT-HERE"])
    err = capsys.readouterr().err  # a serial that is not connected is named as such
    assert code == 2 and "thumb=D360-NOT-HERE (no connected Digit 360 has this USB serial)" in err
    assert hand_hook.opened is None  # nothing was started


def whole_sensors(stack: contextlib.ExitStack, monkeypatch) -> tuple[dict, dict, str]:
    """Four emulated Digit 360 serial streams, each with a camera and microphones on its (faked) USB hub and the
    OpenCV / sounddevice stand-ins: ({finger: emulator}, {tty: Digit360Devices}, the --digit360 value). A test
    may edit the devices before deploy looks for them."""
    monkeypatch.setitem(sys.modules, "sounddevice", Microphones().module)
    emus = {f: stack.enter_context(Digit360Emulator()) for f in FINGERS}
    devices = {emu.path: Digit360Devices(f"/dev/video{2 * i + 2}", f"(hw:{i + 1},0)")
               for i, emu in enumerate(emus.values())}
    monkeypatch.setitem(sys.modules, "cv2", Cameras(tuple(d.camera for d in devices.values())).module)
    monkeypatch.setattr(discovery, "find_digit360_devices", lambda port, sysfs="/sys": devices[port])
    return emus, devices, ",".join(f"{f}={emu.path}" for f, emu in emus.items())


def assert_every_frame_and_sample(image, audio, joint_times: np.ndarray) -> None:
    """A recording of the stand-ins' camera and microphones holds every frame and sample they gave during the run,
    in order: their counters go on without a gap or a repeat, the timestamps increase, and the recording spans the
    run (its first frame and sample in the first second, its last in the last 1.5 s: a loaded 2-core machine starves
    the reader threads, whose frames then come late, and fewer than 30 a second; their count is the machine's)."""
    red = image.data[:, 0, 0, 0].astype(int)  # the stand-in's frame counter: no frame dropped or repeated
    assert len(red) >= 6 and np.all((np.diff(red) % 256) == 1), red
    wave = audio.data[:, 0].astype(int)  # consecutive samples
    assert len(wave) >= 4_800 and np.all((np.diff(wave) + 20_000) % 20_000 == 1)
    for stream in (image, audio):
        assert np.all(np.diff(stream.timestamps) > 0)
        assert 0.0 <= stream.timestamps[0] <= 1.0 and stream.timestamps[-1] >= joint_times[-1] - 1.5, \
            (stream.timestamps[[0, -1]], joint_times[-1])


def test_deploy_records_the_real_sensors_camera_frames_and_microphones(tmp_path, policy, capsys, hand_hook,
                                                                       monkeypatch):
    """With --record, the frames and audio of the cameras and microphones deploy opened go into the session beside
    the serial streams (written from the writer's own thread), every frame and sample in order, and the session
    gives recorded Sparsh-X windows (rotation.data.dataset) as any real session does."""
    from rotation.data.dataset import TouchWindows
    from rotation.data.session_reader import SessionReader

    adapter = build_adapted(policy, ENCODER, ("img", "mic"), touch_every=4).save(tmp_path / "image_audio")
    runs = iter(("run.h5", "run_again.h5"))  # a new session each time: none is overwritten

    def deploy() -> dict:
        with contextlib.ExitStack() as stack:
            _, _, spec = whole_sensors(stack, monkeypatch)
            code = main(["deploy", "--hand", "sim-allegro", "--policy", str(adapter), "--duration", "2.5",
                         "--digit360", spec, "--record", str(tmp_path / next(runs))])
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert code == summary["exit_code"]
        return summary

    summary = again_if_loaded(deploy)
    assert_done_or_load_fault(summary)
    record = Path(summary["record"])  # the session of the run checked
    with SessionReader(record) as r:
        assert r.complete == (summary["exit_code"] == 0)
        joints = r.stream("joints/position")  # a run the machine slowed down: its true, slower timestamps
        spans = []
        for f in FINGERS:
            image, audio = r.stream(f"digit360/{f}/image"), r.stream(f"digit360/{f}/audio")
            assert image.data.shape[1:] == (224, 224, 3) and audio.data.shape[1:] == (2,)
            assert_every_frame_and_sample(image, audio, joints.timestamps)
            assert np.all(image.data[:, :, :, 1] == 20) and np.all(image.data[:, :, :, 2] == 10)
            assert np.array_equal(audio.data[:, 1], -audio.data[:, 0])  # both microphones, kept apart
            # session time (not another clock); a loaded machine may still read frames while the run shuts down
            assert image.timestamps[-1] <= joints.timestamps[-1] + 3.0
            # a window needs the 1.12 s of pressure (its longest history) before its image, and 5 frames before it
            pressure = r.stream(f"digit360/{f}/pressure").timestamps
            history = SERIES_LEN / PRESSURE_RATE + 0.05
            spans.append(len(pressure) > 0 and bool(np.any(image.timestamps[IMAGE_GAP:] >= pressure[0] + history)))
        spans_a_window = all(spans)
    windows = TouchWindows([record], labels=())
    if not spans_a_window:  # a run a loaded machine ended early (the policy's hold fault) may hold no window
        print(f"the run ended after {joints.timestamps[-1]:.2f} s ({summary['fault']}): too short for a window")
        return
    assert len(windows) > 0
    w = windows[len(windows) - 1]
    assert w["image"].shape == (6, 224, 224) and w["audio"].shape == (224, 256) and w["imu"].shape == (224, 3)


def test_record_media_records_the_cameras_and_microphones_for_any_policy(tmp_path, policy, capsys, hand_hook,
                                                                         monkeypatch):
    """--record-media: the student (which reads no touch) records every sensor's frames and audio too, what
    fine-tuning an image or audio adapter on a lab's sessions needs; refused without a recording, with emulated
    sensors, or when a sensor's camera or microphones are not found."""
    from rotation.data.session_reader import SessionReader

    with contextlib.ExitStack() as stack:
        emus, devices, spec = whole_sensors(stack, monkeypatch)
        code = main(["deploy", "--hand", "sim-allegro", "--policy", policy, "--duration", "1.5", "--digit360", spec,
                     "--record", str(tmp_path / "student.h5"), "--record-media"])
        summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert code == summary["exit_code"]
        assert_done_or_load_fault(summary)
        with SessionReader(tmp_path / "student.h5") as r:
            joints = r.stream("joints/position")
            for f in FINGERS:
                assert_every_frame_and_sample(r.stream(f"digit360/{f}/image"), r.stream(f"digit360/{f}/audio"),
                                              joints.timestamps)
                assert len(r.stream(f"digit360/{f}/imu")) > 0
        devices[emus["ring"].path] = Digit360Devices("/dev/video6", None)  # the ring sensor's microphones are gone
        code = main(["deploy", "--hand", "sim-allegro", "--policy", policy, "--duration", "1", "--digit360", spec,
                     "--record", str(tmp_path / "no_mic.h5"), "--record-media"])
        err = capsys.readouterr().err
        lacking = f"no camera or microphones found on the USB hub of the Digit 360 ring={emus['ring'].path}"
        assert code == 2 and lacking in err, err
    for args, message in ((["--digit360", "sim"], "name real Digit 360 sensors"),
                          (["--digit360", "D360-A,D360-B,D360-C,D360-D"], "give --record FILE.h5")):
        extra = ["--record", str(tmp_path / "x.h5")] if "sim" in args else []
        assert main(["deploy", "--hand", "sim-allegro", "--policy", policy, *args, *extra, "--record-media"]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "no_mic.h5").exists() and not (tmp_path / "x.h5").exists()


def test_an_image_and_audio_adapter_fine_tunes_on_sessions_recorded_with_their_media(tmp_path, policy, capsys,
                                                                                    hand_hook, monkeypatch):
    """The real-data path with every modality: a session of the student recorded with --record-media gives windows
    made as a deployed reader makes them (the newest frame at or before the step and the one 5 before it, the
    27,000 audio samples up to that frame), and `rotate finetune-adapter --sessions` trains an image + audio
    adapter on it."""
    from adapters.finetune import job as finetune
    from adapters.real_data import session_samples
    from adapters.session_checks import check_session
    from rotation.bundles import load_bundle
    from rotation.data.session_reader import SessionReader

    windows = ("image", "audio", "imu", "pressure")
    student = load_bundle(policy)
    encoder = load_bundle("teacher").net.extractor.encoder

    def phi(obs):
        return student.net.extractor.z(student._tensors(obs, batched=True)).detach()

    # a loaded 2-core machine can run this deploy far below 20 Hz (a rate fault, exit status 1): fewer steps, fewer
    # samples. Two samples are enough for the window checks below and for the fine-tuning run, so the first cup is
    # recorded again, for longer, into a new session until its session gives two (every session is kept)
    with contextlib.ExitStack() as stack:
        _, _, spec = whole_sensors(stack, monkeypatch)

        def record(name, grasp, duration):
            assert main(["deploy", "--hand", "sim-allegro", "--policy", policy, "--duration", str(duration),
                         "--grasp", str(grasp), "--digit360", spec, "--record-media",
                         "--record", str(tmp_path / "sessions" / f"{name}.h5"),
                         "--properties", f"mass={0.1 + 0.05 * grasp},friction=0.8,com=0,0,0,scale=0.78"]) in (0, 1)
            return tmp_path / "sessions" / f"{name}.h5"

        for attempt, duration in enumerate((4, 8, 16, 16)):
            first = record(f"s0_{attempt}", 0, duration)
            s = session_samples(check_session(first, FINGERS, windows, 20.0), encoder, phi, FINGERS, windows, every=2)
            if len(s) >= 2:
                break
        record("s1", 1, 4)
    capsys.readouterr()
    assert len(s) >= 2, f"{len(s)} samples after a {duration} s session"
    w = s.windows["ring"]
    assert w["image"].shape == (len(s), 2, 224, 224, 3) and w["image"].dtype == np.uint8
    assert w["audio"].shape == (len(s), 2, 27_000) and w["audio"].dtype == np.int16
    with SessionReader(first) as r:
        image, audio = r.stream("digit360/ring/image"), r.stream("digit360/ring/audio")
        for i in (0, len(s) - 1):
            row = int(np.searchsorted(image.timestamps, s.times[i], side="right")) - 1  # newest frame at or before
            np.testing.assert_array_equal(w["image"][i], image.data[[row - 5, row]])
            last = int(np.searchsorted(audio.timestamps, image.timestamps[row], side="right"))
            np.testing.assert_array_equal(w["audio"][i], audio.data[last - 27_000:last].T)
    import tqdm

    monkeypatch.setattr(tqdm.tqdm, "monitor_interval", 0)  # no tqdm monitor thread (this folder checks for leaks)
    cfg = finetune.Config(out=tmp_path / "adapter", sessions=(tmp_path / "sessions",), modalities="img,mic",
                          student=policy, epochs=2, batch_size=8, hidden=(32,), sample_every=4, val_fraction=0.5,
                          progress=False, torch_threads=1, seed=0)
    result = finetune.run(cfg)
    adapter = load_bundle(result.bundle_dir)
    assert adapter.windows == ("image", "audio") and adapter.config.card["samples"] > 0
