"""LEAP hand: Dynamixel Protocol 2.0 tables, the bus over the unmodified dynamixel_sdk, and the driver."""
