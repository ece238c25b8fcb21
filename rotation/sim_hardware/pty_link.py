"""A pseudo-terminal pair in raw mode: the emulator owns the master end, clients open ``path`` like a serial port.

The slave end stays open in the emulator too, so the master never sees EIO between client connections.
Writes to the master are non-blocking: if the client does not read, bytes are dropped and counted, as a real
USB-serial device would lose them. :meth:`disconnect` closes the pair (a pulled cable): the client's next read
fails (pyserial raises ``SerialException``). It takes effect in the thread that calls :meth:`read` (the
emulator's own loop), so no thread ever selects on a descriptor closed (and perhaps reused) under it.
"""

from __future__ import annotations

import os
import select
import threading
import tty


class PtyLink:
    """Master/slave pty pair; ``path`` is the slave device name (e.g. for ``serial.Serial`` or dynamixel-sdk)."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self.master)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self._slave)
        self.dropped_bytes = 0
        self._closed = False
        self._disconnect = threading.Event()
        self._write_lock = threading.Lock()

    @property
    def closed(self) -> bool:
        return self._closed

    def read(self, timeout: float) -> bytes:
        """Bytes the client wrote, waiting at most ``timeout`` s; b'' on timeout or when closed."""
        if self._disconnect.is_set():
            self.close()
        if self._closed:
            return b""
        try:
            ready, _, _ = select.select([self.master], [], [], max(timeout, 0.0))
            if not ready:
                return b""
            return os.read(self.master, 65536)
        except (OSError, ValueError):  # EIO while no client holds the slave, or fd closed under us
            return b""

    def write(self, data: bytes) -> None:
        """Send bytes to the client (dropped and counted if its buffer is full or the link is closed)."""
        with self._write_lock:
            if self._closed:
                self.dropped_bytes += len(data)
                return
            view = memoryview(data)
            while view:
                try:
                    n = os.write(self.master, view)
                except (BlockingIOError, OSError):
                    self.dropped_bytes += len(view)
                    return
                view = view[n:]

    def disconnect(self) -> None:
        """Emulate unplugging the device: both ends close at the reader's next :meth:`read`."""
        self._disconnect.set()

    def close(self) -> None:
        with self._write_lock:
            if self._closed:
                return
            self._closed = True
            for fd in (self.master, self._slave):
                try:
                    os.close(fd)
                except OSError:
                    pass
