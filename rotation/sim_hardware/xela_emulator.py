"""A stand-in for the vendor's ``xela_server``: a local WebSocket server speaking its JSON stream.

``XelaServerEmulator`` listens on 127.0.0.1 (a free port, ``url``), greets each client with
``{"message": "Welcome"}`` and then sends one data message per frame at ``rate_hz`` in the vendor's format
(rotation.hardware.xela.reader.format_message): the frames come from ``frames(k)`` ((368, 3) raw counts in our taxel
order, frame k of the connection; default: the rest reading 32768 with a slow press on the index fingertip).
Tests push raw text (malformed messages) with :meth:`inject`, and ``drop_after`` closes every connection after
that many messages, so a reader's reconnect can be tested. Used by the Xela reader's tests and by `rotate deploy`
rehearsals against a server that is not the real one.
"""

from __future__ import annotations

import gc
import json
import queue
import time
from collections.abc import Callable

import numpy as np

from rotation.hardware.xela.reader import NUM_TAXELS, PAD_START, SAMPLE_HZ, XelaLayout, format_message
from rotation.sim_hardware.worker import EmulatorThread

REST_COUNTS = 32768.0


def press_frames(k: int) -> np.ndarray:
    """Frame k of a gentle periodic press on the index fingertip (Z up to +1500 counts), the rest at 32768."""
    frame = np.full((NUM_TAXELS, 3), REST_COUNTS, np.float32)
    start = PAD_START["index_tip"]
    frame[start : start + 30, 2] += 1500.0 * max(0.0, float(np.sin(2 * np.pi * k / 100.0)))
    return frame


class XelaServerEmulator(EmulatorThread):
    """``with XelaServerEmulator() as server: XelaReader(XelaConfig(url=server.url))`` (see the module docstring)."""

    def __init__(self, frames: Callable[[int], np.ndarray] = press_frames, rate_hz: float = SAMPLE_HZ,
                 layout: XelaLayout | None = None, drop_after: int | None = None) -> None:
        from websockets.sync.server import serve

        self.frames, self.rate_hz, self.layout, self.drop_after = frames, float(rate_hz), layout, drop_after
        self.sent = 0
        """Messages sent over all connections (welcome messages excluded)."""
        self.connections = 0
        self._injected: queue.Queue[str] = queue.Queue()
        self.server = serve(self._handle, "127.0.0.1", 0, compression=None)
        self.url = f"ws://127.0.0.1:{self.server.socket.getsockname()[1]}"
        self._init_worker("xela-server-emulator")

    def inject(self, text: str) -> None:
        """Send ``text`` as the next message (before the next frame) on the current or next connection."""
        self._injected.put(text)

    def _handle(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        self.connections += 1
        period = 1.0 / self.rate_hz
        try:
            ws.send(json.dumps({"message": "Welcome"}))
            k, next_t = 0, time.monotonic()
            while not self._stop.is_set():
                try:
                    text = self._injected.get_nowait()
                except queue.Empty:
                    text = format_message(self.frames(k), self.layout)
                    k += 1
                ws.send(text)
                self.sent += 1
                if self.drop_after is not None and k >= self.drop_after:
                    return  # leaving the handler closes the connection
                next_t += period
                self._stop.wait(max(0.0, next_t - time.monotonic()))
        except ConnectionClosed:
            return

    def _run(self) -> None:
        self.server.serve_forever()

    def close(self) -> None:
        self._stop.set()
        self.server.shutdown()
        super().close()
        # websockets' serve_forever leaves its selector (an epoll descriptor) in a reference cycle: collect it now
        # rather than whenever the cyclic GC runs
        gc.collect()

    def _close_link(self) -> None:
        self.server.socket.close()
