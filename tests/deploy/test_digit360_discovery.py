"""Where a real Digit 360's camera and microphones are: found on the sensor's USB hub (sysfs), by the hub's serial or
the data tty's, and only for the streams the policy reads; a sensor without them is refused by name.

The USB devices cannot be plugged into a test machine: sysfs is a tree of directories and links built as Linux lays
it out (deploy's use of what is found: test_deploy_media.py).
"""

from __future__ import annotations

import os
import types
from pathlib import Path

import pytest

from rotation.deploy.sensors import digit360_windows, find_media
from rotation.deploy.touch import touch_sensors
from rotation.hardware.digit360 import discovery
from rotation.hardware.digit360.discovery import Digit360Devices, find_digit360_devices


def _write(path: Path, **files: str) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (path / name).write_text(text + "\n")
    return path


def _link(node: Path, target: Path) -> None:
    node.mkdir(parents=True, exist_ok=True)
    os.symlink(os.path.relpath(target, node), node / "device")


def fake_sysfs(root: Path) -> Path:
    """Two Digit 360 hubs on a root hub (data tty, camera with a capture and a metadata node, audio card), a
    webcam and a USB serial adapter of other makers, laid out as Linux's sysfs links them."""
    usb = _write(root / "devices" / "pci0000:00" / "0000:00:14.0" / "usb1", idVendor="1d6b", idProduct="0002")
    for hub, tty, videos, card in (("1-2", "ttyACM0", (2, 3), 1), ("1-3", "ttyACM1", (4, 5), 10)):
        h = _write(usb / hub, idVendor="2833", idProduct="6500" if hub == "1-2" else "6502",
                   serial="28BF6A0781" if hub == "1-2" else "28BF6A0799")  # the sensor's serial (Meta's name for it)
        data = _write(h / f"{hub}.1", idVendor="2833", idProduct="4001") / f"{hub}.1:1.0"
        cam = _write(h / f"{hub}.2", idVendor="2833", idProduct="b015") / f"{hub}.2:1.0"
        mic = _write(h / f"{hub}.3", idVendor="2833", idProduct="5001") / f"{hub}.3:1.0"
        for d in (data, cam, mic):
            d.mkdir()
        _link(root / "class" / "tty" / tty, data)
        for index, n in enumerate(videos):
            _link(root / "class" / "video4linux" / f"video{n}", cam)
            _write(root / "class" / "video4linux" / f"video{n}", index=str(index))
        _link(root / "class" / "sound" / f"card{card}", mic)
    webcam = _write(usb / "1-4", idVendor="046d", idProduct="0825") / "1-4:1.0"
    webcam.mkdir()
    _link(root / "class" / "video4linux" / "video0", webcam)
    _write(root / "class" / "video4linux" / "video0", index="0")
    adapter = _write(usb / "1-5", idVendor="0403", idProduct="6001") / "1-5:1.0"
    adapter.mkdir()
    _link(root / "class" / "tty" / "ttyUSB0", adapter)
    _link(root / "class" / "sound" / "card0", root / "devices" / "pci0000:00" / "0000:00:1f.3")
    return root


def test_a_sensors_camera_and_microphones_are_the_ones_on_its_hub(tmp_path):
    sysfs = fake_sysfs(tmp_path / "sys")
    assert find_digit360_devices("/dev/ttyACM0", sysfs) == Digit360Devices("/dev/video2", "(hw:1,0)")
    assert find_digit360_devices("/dev/ttyACM1", sysfs) == Digit360Devices("/dev/video4", "(hw:10,0)")
    assert find_digit360_devices("/dev/ttyUSB0", sysfs) == Digit360Devices()  # a tty of another maker
    assert find_digit360_devices("/dev/pts/7", sysfs) == Digit360Devices()  # a pseudo-terminal: not in sysfs


def test_a_sensor_is_found_by_its_hubs_serial_or_its_data_ttys(tmp_path, monkeypatch):
    """Meta's host code names a Digit 360 by its USB hub's serial; the data tty's own USB serial may differ: either
    finds the sensor, and the listing gives the hub's."""
    sysfs = str(fake_sysfs(tmp_path / "sys"))
    ports = [types.SimpleNamespace(device="/dev/ttyACM0", vid=0x2833, pid=0x4001, serial_number="STM32-AAAA"),
             types.SimpleNamespace(device="/dev/ttyACM1", vid=0x2833, pid=0x4001, serial_number="STM32-BBBB"),
             types.SimpleNamespace(device="/dev/ttyUSB0", vid=0x0403, pid=0x6001, serial_number="28BF6A0781")]
    monkeypatch.setattr(discovery.list_ports, "comports", lambda: ports)
    assert discovery.find_digit360_ports(sysfs=sysfs) == [("/dev/ttyACM0", "28BF6A0781"),
                                                          ("/dev/ttyACM1", "28BF6A0799")]
    assert discovery.find_digit360_ports("28BF6A0799", sysfs) == [("/dev/ttyACM1", "28BF6A0799")]
    assert discovery.find_digit360_ports("STM32-AAAA", sysfs) == [("/dev/ttyACM0", "28BF6A0781")]
    assert discovery.find_digit360_ports("28BF6A0700", sysfs) == []
    assert discovery.hub_serial("/dev/ttyUSB0", sysfs) is None  # another maker's adapter: no Digit 360 hub
    media = find_media({"index": "28BF6A0781", "thumb": "STM32-BBBB"}, ("image", "audio"), sysfs)
    assert media == {"index": Digit360Devices("/dev/video2", "(hw:1,0)"),
                     "thumb": Digit360Devices("/dev/video4", "(hw:10,0)")}


def test_find_media_takes_only_what_the_policy_reads(tmp_path, monkeypatch):
    sysfs = str(fake_sysfs(tmp_path / "sys"))
    connected = [("/dev/ttyACM0", "D360-A")]  # (tty, USB serial), as the real function lists them
    monkeypatch.setattr(discovery, "find_digit360_ports",
                        lambda serial=None, sysfs="/sys": [p for p in connected if serial in (None, p[1])])
    specs = {"index": "D360-A", "thumb": "/dev/ttyACM1", "ring": "D360-GONE", "middle": "sim"}
    assert find_media(specs, ("imu", "pressure"), sysfs) == {}  # serial streams only: nothing to find
    media = find_media(specs, ("image", "pressure"), sysfs)
    assert media == {"index": Digit360Devices("/dev/video2", None), "thumb": Digit360Devices("/dev/video4", None),
                     "ring": Digit360Devices()}  # a sensor that is not connected finds nothing
    media = find_media(specs, ("image", "audio", "imu", "pressure"), sysfs)
    assert media["thumb"] == Digit360Devices("/dev/video4", "(hw:10,0)")
    assert digit360_windows("D360-A", False, media["index"]) == ("image", "audio", "imu", "pressure")
    assert digit360_windows("D360-GONE", False, media["ring"]) == ("imu", "pressure")


def test_touch_sensors_accept_a_real_sensor_with_its_camera_and_microphones():
    policy = types.SimpleNamespace(fingers=("index", "thumb"), windows=("image", "audio", "pressure"), touch_every=4)
    specs = {"index": "D360-A", "thumb": "D360-B"}
    both = {"index": Digit360Devices("/dev/video2", "(hw:1,0)"), "thumb": Digit360Devices("/dev/video4", "(hw:2,0)")}
    assert touch_sensors(policy, "a", specs, emulated=False, media=both) == specs
    no_mic = {**both, "thumb": Digit360Devices("/dev/video4", None)}
    with pytest.raises(ValueError, match="thumb=D360-B gives image, imu, pressure, not audio.*USB hub"):
        touch_sensors(policy, "a", specs, emulated=False, media=no_mic)
