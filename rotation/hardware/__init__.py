"""Hardware drivers, one folder per device, and what they share.

    allegro/   Allegro Hand V4/V5 over CAN: can_bus, protocol (tables), control (host PD), driver
    leap/      LEAP hand over Dynamixel Protocol 2.0: dynamixel_protocol (tables), dynamixel_bus, driver
    digit360/  Digit 360 fingertip: proto_schema + digit360.proto + protocol (the device's serial wire schema, units,
               commands), window, reader
    xela/      Xela uSkin: reader of the xela_server stream
    hand.py    the hand contract both drivers implement; safety.py, the one layer every command passes through;
               realtime.py, scheduling for the control threads

Within a device: bus -> protocol tables (pure functions, data) -> hand (context manager) -> safety. This package
imports neither torch nor mujoco; the emulated hands live in :mod:`rotation.sim_hardware`.

Every hand speaks the same small :class:`rotation.hardware.hand.Hand` protocol: joint positions, velocities and
efforts in the Allegro bus order (index 0-3, middle 4-7, ring 8-11, thumb 12-15), radians, Allegro frame.
"""

from rotation.hardware.hand import Hand, HandFault, HandInfo, HandNotResponding, HandState

__all__ = ["Hand", "HandFault", "HandInfo", "HandNotResponding", "HandState"]
