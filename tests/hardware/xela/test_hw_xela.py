"""The Xela reader: the vendor's xela_server JSON messages (good and malformed) into our taxel order, and the reader
thread against a local WebSocket server (rotation.sim_hardware.xela_emulator) with bad messages and reconnects."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from rotation.hardware.xela import reader as xela
from rotation.hardware.xela.reader import (
    XelaConfig,
    XelaLayout,
    XelaMessageError,
    XelaReader,
    format_message,
    parse_message,
)
from rotation.sim_hardware.xela_emulator import XelaServerEmulator


def frame(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(20_000, 45_000, size=(368, 3)).astype(np.float32)


def recorded_style(f: np.ndarray) -> dict:
    """A message as xela_server sends it: numeric-string keys, model, taxels, hex data (and calibrated forces)."""
    msg = json.loads(format_message(f))
    for entry in msg.values():
        entry["calibrated"] = [0.0] * (3 * entry["taxels"])
    return msg


def test_layout_agrees_with_the_simulated_skin():
    from envs.sensors import xela as sim

    assert [name for name, _ in xela.PADS] == list(sim.PAD_NAMES)
    assert [kind for _, kind in xela.PADS] == [p.kind for p in sim.PADS]
    assert xela.PAD_TAXELS == sim.PAD_TAXELS and xela.NUM_TAXELS == sim.NUM_TAXELS and xela.SAMPLE_HZ == sim.SAMPLE_HZ
    assert all(xela.PAD_START[p.name] == sim.PAD_SLICES[p.name].start for p in sim.PADS)


def test_the_reader_imports_neither_torch_nor_mujoco():
    code = ("import sys, rotation.hardware.xela.reader; "
            "bad = [m for m in ('torch', 'mujoco', 'envs') if m in sys.modules]; "
            "print(bad); sys.exit(bool(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def test_a_recorded_style_message_parses_into_our_taxel_order():
    f = frame()
    text = json.dumps(recorded_style(f))
    assert np.array_equal(parse_message(text), f)
    assert parse_message(json.dumps({"message": "Welcome"})) is None
    # sensor 1 holds 30 taxels (a fingertip board): its hex words are our index_tip taxels 0..29, X Y Z each
    msg = json.loads(text)
    first = [int(w, 16) for w in msg["1"]["data"].split(",")]
    assert msg["1"]["taxels"] == 30 and first[:3] == f[0].tolist() and first[-3:] == f[29].tolist()
    # another board order: vendor sensor 1 is our middle fingertip
    order = list(xela.VENDOR_SENSOR_PADS)
    order[0], order[4] = order[4], order[0]
    layout = XelaLayout(tuple(order))
    moved = parse_message(text, layout)
    start = xela.PAD_START["middle_tip"]
    assert np.array_equal(moved[start : start + 30], f[:30])
    assert np.array_equal(parse_message(format_message(f, layout), layout), f)  # both ways with one layout
    with pytest.raises(ValueError, match="sensor_pads: need each of our 18 pads exactly once"):
        XelaLayout(tuple(order[:-1]))


@pytest.mark.parametrize(("edit", "message"), [
    (lambda m: "not json {", r"not JSON"),
    (lambda m: json.dumps([1, 2]), r"expected a JSON object, got list"),
    (lambda m: json.dumps({"status": "ok"}), r"no sensor entries"),
    (lambda m: json.dumps({k: v for k, v in m.items() if k != "7"}), r"missing \['7'\]"),
    (lambda m: json.dumps({**m, "19": m["1"]}), r"unexpected \['19'\]"),
    (lambda m: json.dumps({**m, "2": {**m["2"], "taxels": 30}}), r"sensor 2: 30 taxels, but it maps to a pad of 16"),
    (lambda m: json.dumps({**m, "3": {**m["3"], "data": m["3"]["data"] + ",7fff"}}), r"sensor 3: 49 values"),
    (lambda m: json.dumps({**m, "4": {**m["4"], "data": m["4"]["data"].replace(m["4"]["data"][:4], "zz12", 1)}}),
     r"sensor 4: 'zz12' is not a hexadecimal number"),
    (lambda m: json.dumps({**m, "5": {**m["5"], "data": m["5"]["data"].replace(m["5"]["data"][:4], "1ffff", 1)}}),
     r"sensor 5: values outside the 16-bit range"),
    (lambda m: json.dumps({**m, "6": "7fff,7fff"}), r"sensor 6: expected an object with a 'data' string"),
])
def test_malformed_messages_are_clear_errors(edit, message):
    with pytest.raises(XelaMessageError, match=message):
        parse_message(edit(recorded_style(frame())))


def test_bad_urls_and_settings_are_refused():
    with pytest.raises(ValueError, match="skin: 'http://x:5000' is not a WebSocket URL"):
        xela.parse_url("http://x:5000", "skin")
    with pytest.raises(ValueError, match="not a WebSocket URL"):
        XelaConfig(url="localhost:5000")
    with pytest.raises(ValueError, match="reconnect_s"):
        XelaConfig(reconnect_s=0.0)


def test_the_reader_skips_bad_messages_and_reconnects():
    frames = [frame(k) for k in range(5)]
    with XelaServerEmulator(frames=lambda k: frames[k % 5], rate_hz=200.0, drop_after=40) as server:
        server.inject("garbage")
        server.inject(json.dumps({"1": {"taxels": 30}}))
        server.inject(json.dumps({"message": "calibrating"}))  # a status message: neither a frame nor an error
        with XelaReader(XelaConfig(url=server.url, reconnect_s=0.05)) as reader:
            deadline = time.monotonic() + 5.0
            while (reader.counters["connects"] < 2 or reader.counters["frames"] < 60) and time.monotonic() < deadline:
                time.sleep(0.02)
            counters = dict(reader.counters)
            t, v = reader.frames.snapshot()
            after = reader.counters["frames"]  # frames keep arriving: the snapshot lies between the two counts
            reader.check_fresh()
    assert counters["skipped"] == 2, counters  # the garbage and the incomplete message; the status one ignored
    assert counters["connects"] >= 2 and counters["disconnects"] >= 1, counters  # the server dropped us: reconnected
    assert counters["frames"] >= 60 and counters["frames"] <= len(t) <= after and np.all(np.diff(t) >= 0)
    assert np.array_equal(v[0], frames[0]) and np.array_equal(v[4], frames[4])  # in order, our taxel order
    assert np.array_equal(v[40], frames[0])  # the first frame of the second connection
    with pytest.raises(xela.SensorStale, match="no frame for"):
        reader.check_fresh(now=time.monotonic() + 1.0)


def test_no_server_is_reported_not_raised():
    with XelaServerEmulator() as server:
        url = server.url
    assert xela.probe_server(url, timeout_s=0.5) != ""  # closed: refused, one line
    with XelaReader(XelaConfig(url=url, reconnect_s=0.05)) as reader:
        time.sleep(0.3)
    assert reader.counters["frames"] == 0 and reader.counters["disconnects"] >= 1
    assert "connection to" in reader.last_error
