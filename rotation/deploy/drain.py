"""The thread that moves the sensors' new samples into the recording beside the control loop, so a drain never
delays a control step.
"""

from __future__ import annotations

import logging
import math
import threading
import time

log = logging.getLogger("rotation.deploy.loop")  # the loop's own logger: its messages are the loop's

SETTLE_S = 3.0
"""Longest wait (s), with the motors off, for sensors whose samples of the run's last moments are still on their
way (the emulated fingertips of the vendor-kinematics hand fell 1.3 s behind on a loaded 2-core machine)."""
STILL_S = 0.3
"""A sensor whose newest sample has not advanced for this long (s) is stalled or unplugged: not waited for."""
CAUGHT_UP_S = 0.01
"""A sensor whose newest sample is at most this long (s) before the run's last step has caught up."""
POLL_S = 0.02


class Drains:
    """Several sensor drains (Digit 360, skin) behind one ``drain(append)``."""

    def __init__(self, drains: list) -> None:
        self.drains = drains

    def drain(self, append) -> None:
        for d in self.drains:
            d.drain(append)

    def newest(self) -> dict[str, float]:
        """Each sensor's newest sample time (host s), by name (``digit360 index``, ``skin``)."""
        out: dict[str, float] = {}
        for d in self.drains:
            out.update(d.newest())
        return out


class DrainThread:
    """Moves the sensors' samples into the recording every ``every_s`` from its own thread, so that the control
    loop never waits for it: a drain of four fingertips' camera frames and audio is a few ms on an idle machine but
    took 250-500 ms on a busy 2-core one (every step of it waits its turn for the interpreter's lock among the
    sensors' threads), and on the loop's thread it cost the run most of its 20 Hz slots. A failed drain (a
    SessionError) is kept and raised by :meth:`check`, which the loop calls every step."""

    def __init__(self, drain: Drains, append, every_s: float) -> None:
        self.drain, self.append, self.every_s = drain, append, every_s
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="deploy-drain", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                self.drain.drain(self.append)
            except BaseException as err:  # noqa: BLE001 -- handed to the loop's thread by check()
                self.error = err
                return

    def check(self) -> None:
        """Raise the drain's error, if one ended it."""
        if self.error is not None:
            raise self.error

    def stop(self, final_drain: bool) -> None:
        """Stop. ``final_drain`` (a run that ended well): wait for a drain in progress, then move what came since.
        Otherwise (a fault: the motors go off first) nothing is waited for here; :meth:`drain_rest` moves the
        samples of the run's last moments once the hand is off."""
        self._stop.set()
        if final_drain:
            self._thread.join()
            self.check()
            self.drain.drain(self.append)

    def settle(self, t_end: float, cap_s: float = SETTLE_S) -> dict[str, float]:
        """Wait (at most ``cap_s``) until every sensor has delivered its samples up to ``t_end`` (host s, the run's
        last step), so that :meth:`drain_rest` records the run to its end: on a loaded machine the emulated
        fingertips' samples reach their readers up to a second late. A sensor whose newest sample stops advancing
        for ``STILL_S`` (stalled or unplugged) is not waited for. Returns how far (s) each sensor that did not
        catch up ends before ``t_end`` (logged); never raises (it runs while the run's hand is being closed)."""
        try:
            deadline = time.monotonic() + cap_s
            seen: dict[str, tuple[float, float]] = {}  # sensor -> (newest sample time, when it last advanced)
            while True:
                now = time.monotonic()
                # (a sensor that never delivered a sample is not waited for: its drain has said so already)
                short = {name: t for name, t in self.drain.newest().items()
                         if math.isfinite(t) and t < t_end - CAUGHT_UP_S}
                for name, t in short.items():
                    if name not in seen or t > seen[name][0]:
                        seen[name] = (t, now)
                waiting = [n for n in short if now - seen[n][1] < STILL_S]
                if not waiting or now >= deadline:
                    break
                time.sleep(POLL_S)
        except Exception as err:  # noqa: BLE001 -- the recording keeps what arrived; say so
            log.warning("recording: could not wait for the sensors' last samples: %s", err)
            return {}
        behind = {name: t_end - t for name, t in short.items()}
        for name, lag in behind.items():
            log.warning("recording: %s's samples end %.2f s before the run's last step", name, lag)
        return behind

    def drain_rest(self, timeout_s: float) -> bool:
        """Once the motors are off (after a fault, or after a run that ended well): wait up to ``timeout_s`` for a
        drain in progress, then move the samples that came since (the moments before a fault are those a lab most
        wants to look at; :meth:`settle` first lets late sensors deliver them). False (logged) when they could not
        be recorded: a drain still busy, or the recording failed."""
        self._stop.set()
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            log.warning("recording: a drain still busy %.1f s after the run; the sensors' last samples are not in "
                        "the session", timeout_s)
            return False
        if self.error is not None:
            log.warning("recording: the sensors' last samples are not in the session (a drain failed: %s)",
                        self.error)
            return False
        try:
            self.drain.drain(self.append)
        except Exception as err:  # noqa: BLE001 -- the hand is off; the run's outcome is already decided
            log.error("recording: the sensors' last samples could not be recorded: %s", err)
            return False
        return True
