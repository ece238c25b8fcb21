"""Allegro Hand V4/V5 over CAN: the bus, the protocol tables, the host-side control law and the driver."""
