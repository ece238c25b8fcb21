"""The session format: round trip, crash safety (a writer killed with SIGKILL) and every bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest

from rotation.data.session import FORMAT_VERSION, STREAMS, SessionError, SessionMeta, StreamSetup
from rotation.data.session_reader import SessionReader
from rotation.data.session_writer import SessionWriter

META = SessionMeta(source="sim", object="cylinder", control_hz=20.0, seed=7, properties={"mass": 0.1})


def write_basic(path, n=40, **meta_kw):
    """A small valid session: joints at 20 Hz, one fingertip's IMU at 400 Hz and pressure at 200 Hz."""
    meta = SessionMeta(**{**META.__dict__, **meta_kw})
    streams = [StreamSetup("joints/position", rate_hz=20.0), "digit360/index/imu", "digit360/index/pressure"]
    with SessionWriter(path, meta, streams) as w:
        t = np.arange(n) / 20.0
        w.append("joints/position", np.tile(np.arange(n, dtype=np.float32)[:, None], (1, 16)), t)
        w.append("digit360/index/imu", np.zeros((20 * n, 3), np.float32), np.arange(20 * n) / 400.0)
        w.append("digit360/index/pressure", np.full((10 * n, 1), 1000.0, np.float32), np.arange(10 * n) / 200.0)
    return path


def test_round_trip(tmp_path):
    path = write_basic(tmp_path / "s.h5")
    with SessionReader(path, require=["joints/position"]) as r:
        assert r.complete and r.version == FORMAT_VERSION
        assert r.meta.source == "sim" and r.meta.seed == 7 and r.meta.properties == {"mass": 0.1}
        assert r.meta.created and r.meta.software_version
        assert r.names == ("digit360/index/imu", "digit360/index/pressure", "joints/position")
        q = r.stream("joints/position")
        assert q.data.shape == (40, 16) and q.rate_hz == 20.0 and q.timestamps[-1] == pytest.approx(39 / 20)
        assert np.array_equal(q.data[:, 0], np.arange(40))
        assert r.fingers_with_touch() == ("index",)


def test_a_background_writer_keeps_every_sample_and_reports_a_failed_write(tmp_path, monkeypatch):
    """background=True: appends only queue, the writer's thread writes and flushes; everything appended is on disk
    after close, in order, and a write that failed on that thread is raised by the next append."""
    streams = [StreamSetup("digit360/index/image", shape=(8, 8, 3)), "digit360/index/audio"]
    with SessionWriter(tmp_path / "bg.h5", META, streams, flush_interval_s=0.01, background=True) as w:
        for k in range(60):
            w.append("digit360/index/image", np.full((1, 8, 8, 3), k, np.uint8), np.array([k / 30.0]))
            w.append("digit360/index/audio", np.arange(1600 * k, 1600 * (k + 1)).reshape(800, 2) % 30000,
                     (np.arange(800) + 800 * k) / 48_000.0)
            if k == 30:
                deadline = time.monotonic() + 5.0
                while w.flushed["digit360/index/image"] == 0 and time.monotonic() < deadline:
                    time.sleep(0.01)
                assert w.flushed["digit360/index/image"] > 0  # written meanwhile by the writer's thread
    with SessionReader(tmp_path / "bg.h5") as r:
        assert r.complete
        assert r.stream("digit360/index/image").data[:, 0, 0, 0].tolist() == list(range(60))
        audio = r.stream("digit360/index/audio").data
        assert audio.shape == (48_000, 2) and np.array_equal(audio.ravel(), np.arange(96_000) % 30000)
    w = SessionWriter(tmp_path / "fail.h5", META, streams, flush_interval_s=0.01, background=True)

    def disk_full():
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(w._file, "flush", disk_full)
    w.append("digit360/index/image", np.zeros((1, 8, 8, 3), np.uint8), np.array([0.0]))
    deadline = time.monotonic() + 5.0
    while w._error is None and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(SessionError, match="writing failed: .*No space left"):
        w.append("digit360/index/image", np.zeros((1, 8, 8, 3), np.uint8), np.array([0.1]))
    monkeypatch.undo()
    w.abort()
    with SessionReader(tmp_path / "fail.h5") as r:
        assert not r.complete


def test_every_stream_of_the_registry_can_be_written(tmp_path):
    setups = []
    for name, spec in STREAMS.items():
        shape = tuple(4 if d is None else d for d in spec.shape)
        setups.append(StreamSetup(name, rate_hz=spec.rate_hz or 50.0, shape=shape))
    with SessionWriter(tmp_path / "all.h5", META, setups) as w:
        for s in setups:
            rate = s.rate_hz
            w.append(s.name, np.zeros((4, *s.shape), STREAMS[s.name].dtypes[0]), np.arange(4) / rate)
    with SessionReader(tmp_path / "all.h5") as r:
        assert set(r.names) == set(STREAMS)
        for name in STREAMS:
            assert len(r.stream(name)) == 4


_KILLED_WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    from rotation.data.session import SessionMeta, StreamSetup
    from rotation.data.session_writer import SessionWriter

    meta = SessionMeta(source="real", object="cup", control_hz=100.0)
    w = SessionWriter(sys.argv[1], meta, [StreamSetup("joints/position", rate_hz=100.0)], flush_interval_s=0.02)
    last, i = 0, 0
    while True:  # runs until killed
        w.append("joints/position", np.full((1, 16), i, np.float32), [i / 100.0])
        i += 1
        if w.flushed["joints/position"] != last:
            last = w.flushed["joints/position"]
            print(last, flush=True)
""")


def test_writer_killed_with_sigkill_leaves_a_readable_file(tmp_path):
    path = tmp_path / "killed.h5"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(path)], stdout=subprocess.PIPE, text=True,
                            env=env)
    flushes = []
    try:
        for line in proc.stdout:
            flushes.append(int(line))
            if len(flushes) >= 4:
                break
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    assert len(flushes) >= 4, "the writer never flushed"
    assert proc.returncode == -signal.SIGKILL
    with SessionReader(path) as r:
        assert not r.complete
        q = r.stream("joints/position")
        n = len(q)
        assert n >= flushes[-1]  # everything flushed before the kill is there
        assert np.array_equal(q.data[:, 0], np.arange(n)) and np.allclose(q.timestamps, np.arange(n) / 100.0)


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(SessionError, match="unknown stream 'joints/velocity'"):
        SessionWriter(tmp_path / "a.h5", META, [StreamSetup("joints/velocity", rate_hz=20.0)])
    with pytest.raises(SessionError, match="runs at 400.0 Hz"):
        SessionWriter(tmp_path / "b.h5", META, [StreamSetup("digit360/index/imu", rate_hz=100.0)])
    with pytest.raises(SessionError, match="needs a positive rate_hz"):
        SessionWriter(tmp_path / "c.h5", META, ["joints/position"])
    with pytest.raises(SessionError, match="needs an explicit shape"):
        SessionWriter(tmp_path / "d.h5", META, ["digit360/index/image"])
    w = SessionWriter(tmp_path / "e.h5", META, [StreamSetup("joints/position", rate_hz=20.0)])
    with pytest.raises(SessionError, match=r"e\.h5, stream 'joints/position': expected data \(n, 16\)"):
        w.append("joints/position", np.zeros((2, 15)), [0.0, 0.05])
    with pytest.raises(SessionError, match="non-finite"):
        w.append("joints/position", np.full((1, 16), np.nan), [0.0])
    w.append("joints/position", np.zeros((1, 16)), [1.0])
    with pytest.raises(SessionError, match="non-decreasing"):
        w.append("joints/position", np.zeros((1, 16)), [0.5])
    with pytest.raises(SessionError, match="not declared"):
        w.append("labels/z", np.zeros((1, 8)), [1.0])
    w.close()
    with pytest.raises(SessionError, match="file exists"):
        SessionWriter(tmp_path / "e.h5", META, [StreamSetup("joints/position", rate_hz=20.0)])


def _edit(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda f: f.attrs.__setitem__("format_version", FORMAT_VERSION + 1), "format version 2 is newer"),
        (lambda f: f.attrs.__delitem__("format_version"), "no format_version"),
        (lambda f: f["streams/digit360/index/imu/data"].attrs.__setitem__("rate_hz", 100.0),
         r"stream 'digit360/index/imu': declared rate 100.0 Hz, the format needs 400.0 Hz"),
        (lambda f: f["streams/joints/position/timestamps"].__setitem__(slice(None), np.arange(40) / 10.0),
         r"stream 'joints/position': timestamps step 0.1 s, but rate_hz=20.0"),
        (lambda f: f["streams/digit360/index/pressure/data"].__setitem__(5, np.nan),
         r"stream 'digit360/index/pressure': non-finite samples \(first at index 5"),
        (lambda f: f["streams/joints/position/timestamps"].__setitem__(3, 10.0),
         r"stream 'joints/position': timestamps are not finite and non-decreasing"),
    ],
    ids=["newer-version", "no-version", "wrong-rate-attr", "wrong-rate-timestamps", "non-finite", "unordered"],
)
def test_reader_rejects_bad_files(tmp_path, edit, match):
    path = write_basic(tmp_path / "bad.h5")
    _edit(path, edit)
    with pytest.raises(SessionError, match=match) as info:
        with SessionReader(path) as r:
            for name in r.names:
                r.stream(name)
    assert "bad.h5" in str(info.value) and isinstance(info.value, ValueError)


def test_reader_keeps_an_incomplete_session_off_its_rate_with_a_warning(tmp_path, caplog):
    """A run that ended in a fault (a control loop that could not hold 20 Hz) leaves an incomplete session whose
    joint timestamps are the true, slower ones: kept and read, with a warning; a complete one is refused."""
    path = write_basic(tmp_path / "slow.h5")

    def slow_and_interrupted(f):
        f["streams/joints/position/timestamps"][:] = np.arange(40) * 0.062
        f.attrs["complete"] = False

    _edit(path, slow_and_interrupted)
    with SessionReader(path) as r, caplog.at_level("WARNING", logger="rotation.data.session"):
        joints = r.stream("joints/position")
        assert not r.complete and len(joints) == 40 and joints.timestamps[-1] == pytest.approx(39 * 0.062)
    assert "timestamps step 0.062 s, but rate_hz=20.0" in caplog.text and "not complete" in caplog.text


def test_reader_keeps_a_complete_session_whose_sensor_the_host_read_slowly(tmp_path, caplog):
    """A sensor stream at its fixed rate is stamped on arrival: a busy host that took a third of a sensor's samples
    gives a complete session whose stream is slower than declared. It is kept, with a warning naming the rate it
    had; a declared-rate stream (the control loop's joints) off its rate in a complete session is still refused."""
    path = write_basic(tmp_path / "slow_imu.h5")
    _edit(path, lambda f: f["streams/digit360/index/imu/timestamps"].__setitem__(slice(None), np.arange(800) * 0.0075))
    with SessionReader(path) as r, caplog.at_level("WARNING", logger="rotation.data.session"):
        imu = r.stream("digit360/index/imu")
        assert r.complete and len(imu) == 800 and imu.timestamps[-1] == pytest.approx(799 * 0.0075)
    _edit(path, lambda f: f["streams/joints/position/timestamps"].__setitem__(slice(None), np.arange(40) * 0.1))
    with SessionReader(path) as r, pytest.raises(SessionError, match=r"'joints/position': timestamps step 0\.1 s"):
        r.stream("joints/position")
    assert "timestamps step 0.0075 s, but rate_hz=400.0" in caplog.text
    assert "it came at 133 of its declared 400 samples a second" in caplog.text


def test_reader_rejects_wrong_shape_and_missing_streams(tmp_path):
    path = write_basic(tmp_path / "shape.h5")

    def widen(f):  # an IMU stream with 4 axes: refused, never reshaped
        del f["streams/digit360/index/imu/data"]
        d = f.create_dataset("streams/digit360/index/imu/data", data=np.zeros((800, 4), np.float32))
        d.attrs["rate_hz"] = 400.0

    _edit(path, widen)
    with SessionReader(path) as r, pytest.raises(SessionError, match=r"'digit360/index/imu': sample shape \(4,\)"):
        r.stream("digit360/index/imu")
    with pytest.raises(SessionError, match=r"shape\.h5: missing stream\(s\) digit360/thumb/audio"):
        SessionReader(path, require=["digit360/thumb/audio"])
    with SessionReader(path) as r, pytest.raises(SessionError, match="'labels/z': missing"):
        r.stream("labels/z")
    with pytest.raises(SessionError, match="no such file"):
        SessionReader(tmp_path / "nope.h5")
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(SessionError, match="not a readable HDF5 file"):
        SessionReader(tmp_path / "junk.h5")


def test_metadata_is_validated():
    with pytest.raises(SessionError, match="source must be 'sim' or 'real'"):
        SessionMeta(source="lab", object="cup", control_hz=20.0)
    with pytest.raises(SessionError, match="control_hz"):
        SessionMeta(source="real", object="cup", control_hz=0.0)
