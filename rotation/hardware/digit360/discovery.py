"""Finding attached Digit 360 sensors: their serial data ports by USB identity, and the camera and microphones
on each sensor's own USB hub.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from serial.tools import list_ports

USB_VENDOR = 0x2833
USB_PRODUCT_DATA = 0x4001
USB_PRODUCT_HUBS = (0x6500, 0x6502)
"""Product ids of the USB hub that each Digit 360 is (its camera, microphones and data tty are its children)."""


def find_digit360_ports(serial_number: str | None = None, sysfs: str | Path = "/sys") -> list[tuple[str, str]]:
    """(device path, serial) of the Digit 360 data ttys, optionally only the one with ``serial_number``.

    The serial is the sensor's: its USB hub's serial number, which Meta's host code names a sensor by (udev
    ``ID_SERIAL_SHORT`` of the hub, docs/reference/digit360_protocol.md section 4), read from sysfs; where the hub is
    not found, the data tty's own USB serial. ``serial_number`` matches either, so a setup written with either
    finds its sensor."""
    found = []
    for p in list_ports.comports():
        if p.vid == USB_VENDOR and p.pid == USB_PRODUCT_DATA:
            hub = hub_serial(p.device, sysfs)
            if serial_number is None or serial_number in (hub, p.serial_number):
                found.append((p.device, hub or p.serial_number or ""))
    return found


def hub_serial(port: str, sysfs: str | Path = "/sys") -> str | None:
    """The serial number of the Digit 360 USB hub above the data tty ``port`` (its sysfs ``serial`` file), None when
    the tty is not under one (a pseudo-terminal, another maker's adapter) or the hub reports none."""
    hub = _hub_of(Path(sysfs), port)
    if hub is None:
        return None
    try:
        return (hub / "serial").read_text().strip() or None
    except OSError:
        return None


def _hub_of(root: Path, port: str) -> Path | None:
    tty = root / "class" / "tty" / Path(port).resolve().name / "device"
    if not tty.exists():
        return None
    for parent in tty.resolve().parents:
        if _usb_id(parent, "idVendor") == USB_VENDOR and _usb_id(parent, "idProduct") in USB_PRODUCT_HUBS:
            return parent
    return None


@dataclass(frozen=True)
class Digit360Devices:
    """The camera and microphones of one Digit 360, as :class:`Digit360Config` takes them (None: not found)."""

    camera: str | None = None
    """V4L2 capture node, e.g. ``/dev/video2`` (OpenCV opens it by path)."""
    audio: str | None = None
    """sounddevice input device: the name substring ``(hw:N,0)`` of the sensor's ALSA card N."""


def _usb_id(path: Path, name: str) -> int | None:
    try:
        return int((path / name).read_text().strip(), 16)
    except (OSError, ValueError):
        return None


def _node_number(path: Path) -> int:
    digits = "".join(ch for ch in path.name if ch.isdigit())
    return int(digits) if digits else 1 << 30


def find_digit360_devices(port: str, sysfs: str | Path = "/sys") -> Digit360Devices:
    """The camera and microphones on the same USB hub as the Digit 360 whose data tty is ``port``.

    A Digit 360 is a USB hub (vendor 0x2833, product 0x6500 or 0x6502) whose children are the data tty, a UVC
    camera and a USB audio device (docs/reference/hardware.md, section 4). Linux's sysfs links each tty, V4L2 node and
    ALSA card to its USB interface (``<sysfs>/class/{tty,video4linux,sound}/<node>/device``); the camera and the
    microphones of a sensor are the ones whose interface lies under the hub above its tty. A camera has several
    V4L2 nodes (capture, metadata): the capture one has ``index`` 0. Nothing found: None in that field (a tty that
    is not a Digit 360's, e.g. a pseudo-terminal, has neither). ``sysfs``: another root (tests).
    """
    root = Path(sysfs)
    hub = _hub_of(root, port)
    if hub is None:
        return Digit360Devices()

    def under_hub(node: Path) -> bool:
        link = node / "device"
        return link.exists() and hub in link.resolve().parents

    cameras = [n for n in sorted((root / "class" / "video4linux").glob("video*"), key=_node_number)
               if under_hub(n) and (not (n / "index").exists() or (n / "index").read_text().strip() == "0")]
    cards = [n for n in sorted((root / "class" / "sound").glob("card*"), key=_node_number) if under_hub(n)]
    return Digit360Devices(camera=f"/dev/{cameras[0].name}" if cameras else None,
                           audio=f"(hw:{_node_number(cards[0])},0)" if cards else None)
