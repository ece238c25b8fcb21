"""Digit 360 fingertip: the serial stream's schema, the reader (serial, camera, audio) and its windows."""
