"""The emulators' common lifecycle: one daemon thread that answers the bus until the emulator is closed."""

from __future__ import annotations

import threading
from typing import Self


class EmulatorThread:
    """Base class: ``with Emulator(...) as emu:`` starts the thread running ``_run``; leaving stops it.

    Subclasses call :meth:`_init_worker` in their constructor, implement ``_run`` (loop until ``self._stop`` is
    set) and ``_close_link`` (release the bus, pty or transport after the thread has stopped).
    """

    _stop: threading.Event
    _thread: threading.Thread

    def _init_worker(self, name: str) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def _run(self) -> None:
        raise NotImplementedError

    def _close_link(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the thread (waits up to 2 s) and release the link; safe to call twice."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._close_link()
