"""Open a python-can bus from one ``INTERFACE:CHANNEL`` string.

Supported (docs/reference/hardware.md sections 1 and 6):

- ``socketcan:can0`` (Linux; bring the link up first with
  ``ip link set can0 up type can bitrate 1000000 restart-ms 100``: without restart-ms the controller stays in
  BUS-OFF after frames went unacknowledged while the hand was off);
- ``pcan:PCAN_USBBUS1`` (PEAK PCAN-USB, bitrate 1 Mbit/s);
- ``slcan:/dev/ttyACM0`` (serial-line CAN adapters; bitrate 1 Mbit/s, ``sleep_after_open=0``);
- ``virtual:NAME`` (in-process bus for tests and the emulator; all buses on NAME see each other's frames).
"""

from __future__ import annotations

import can

BITRATE = 1_000_000
"""Allegro CAN bitrate, bit/s (docs/reference/hardware.md section 1: CAN 2.0 at 1 Mbit/s)."""

INTERFACES = ("socketcan", "pcan", "slcan", "virtual")


def parse_can_spec(spec: str) -> tuple[str, str]:
    """``'INTERFACE:CHANNEL'`` -> (interface, channel); ValueError naming the valid forms otherwise."""
    if not isinstance(spec, str) or ":" not in spec:
        raise ValueError(f"CAN bus {spec!r}: expected INTERFACE:CHANNEL with INTERFACE one of {', '.join(INTERFACES)}"
                         " (e.g. socketcan:can0, pcan:PCAN_USBBUS1, slcan:/dev/ttyACM0, virtual:test)")
    interface, channel = spec.split(":", 1)
    interface = interface.strip().lower()
    channel = channel.strip()
    if interface not in INTERFACES:
        raise ValueError(f"CAN bus {spec!r}: unknown interface {interface!r}; choose one of {', '.join(INTERFACES)}")
    if not channel:
        raise ValueError(f"CAN bus {spec!r}: empty channel after {interface!r}:")
    return interface, channel


def open_bus(spec: str, **kwargs: object) -> can.BusABC:
    """Open the bus named by ``spec``; extra keyword arguments go to ``can.Bus``.

    Raises ValueError for a malformed spec and ``can.CanInitializationError`` (with the spec in the message)
    when the adapter cannot be opened.
    """
    interface, channel = parse_can_spec(spec)
    options: dict[str, object] = {}
    if interface in ("pcan", "slcan"):
        options["bitrate"] = BITRATE
    if interface == "slcan":
        options["sleep_after_open"] = 0.0  # the adapter is ready once the tty is open (python-can default is 2 s)
    options.update(kwargs)
    try:
        return can.Bus(interface=interface, channel=channel, **options)
    except (can.CanError, OSError) as err:
        raise can.CanInitializationError(f"could not open CAN bus {spec!r}: {err}") from err
