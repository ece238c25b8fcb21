"""Touch during deploy: a tactile adapter's correction, refreshed on its own thread, with the documented fallback.

A touch-reading policy (an adapter bundle, adapters.bundle.AdaptedPolicy) is its student plus a latent correction
computed from the Digit 360 windows of every fingertip it reads. Touch tells friction and mass, which change
slowly, and encoding four fingertips costs more than a control period, so (as in training and evaluation) the
correction is refreshed every ``policy.touch_every`` control steps and held in between:

- :class:`TouchWorker` runs the refreshes on its own thread (torch limited to one thread there, so the control loop
  and the drivers keep the other core). When a refresh is due (``touch_every`` steps after the previous one) the
  loop hands that step's observation over without waiting, once the policy has acted on it (so the refresh runs
  in the step's slack, not beside the policy's inference); the worker reads ``reader.window()`` of each fingertip
  at that moment, batches them (N = 1) and computes ``policy.correction(windows, obs)``. A refresh that falls due
  while the previous one is still running starts at the first step after it (counted as delayed; a worker that is
  slower than the refresh period is reported once, with its time).
- The loop never waits for touch: every step acts with the newest finished correction, or as the student alone.

Fallback (the student alone, ``correction=None``): no usable correction because a fingertip's stream stalled
(``SensorStale``), a reader raised, a window lacks a modality the adapter reads, the embeddings were not finite
(``TouchUnavailable``), the worker itself raised (a bug: logged with its traceback), or the newest correction is
older than ``max_age_s`` (the worker is behind or hung; ``STALE_REFRESHES`` refresh periods, at least
``MIN_STALE_S``). Entering the fallback logs ONE warning naming the cause; leaving it logs one info line (a cause
that keeps coming back is warned about again every ``REPEAT_WARN_EVERY``-th time, at info in between). Touch never
stops the hand.

Start-up (:func:`wait_for_touch`): the sensors open, and their windows fill, BEFORE the motors go on: a hand that
only holds its start pose while the windows fill loses its grasp within a few hundred ms (measured on the emulated
hand: the fingertips had left the cup before the first correction, and the adapter never saw a grasp again). The
encoder runs once on those first windows (its first call allocates). Once the hand is on, the loop starts at once;
the first refresh is asked for at step 0 and the student acts alone until it arrives (a few steps; logged at info,
counted in ``fallback_steps``), as it does whenever touch is unusable.

Which sensors a touch-reading policy needs (:func:`touch_sensors`) is checked before anything starts: on an emulated
hand without ``--digit360`` the emulated fingertips are started for it; on a real hand every fingertip the adapter
reads must be named by ``--digit360`` and stream every window it reads (the serial streams, and the camera and
microphones found on each sensor's USB hub when the adapter reads them), else it is a ValueError (motors never on).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from rotation.deploy.sensors import digit360_windows

log = logging.getLogger(__name__)
WARM_UP_S = 5.0
"""Longest wait (s), before the motors go on, for every fingertip's windows (they need about 1.2 s of history after
the sensors open); without them by then the run starts as the student alone until they come."""


def reads_touch(policy: Any) -> bool:
    """True for a policy that reads touch (a tactile adapter bundle: ``correction``, ``fingers``, ``windows``)."""
    return all(hasattr(policy, name) for name in ("correction", "fingers", "windows", "touch_every"))


def touch_sensors(policy: Any, name: str, specs: dict[str, str], emulated: bool,
                  media: Mapping[str, Any] | None = None) -> dict[str, str]:
    """The ``--digit360`` sensors to open for ``policy`` ({finger: spec}, as rotation.deploy.sensors.parse_digit360).

    Emulated hand without ``--digit360``: emulated fingertips on every finger ('sim', logged). Otherwise every
    fingertip the adapter reads must be named and its sensor must give every window the adapter reads (a real
    sensor: its serial streams, plus the camera and microphones in ``media``, rotation.deploy.sensors.find_media);
    ValueError (naming the fingers or windows, and the fix) when not, before anything is started. A skin adapter
    (Sparsh-skin) is refused the same way: deploy reads Digit 360 fingertips only.
    """
    if getattr(policy, "sensor", "digit360") != "digit360":
        raise ValueError(f"policy {name!r} reads the Xela skin; deploy runs Digit 360 adapters only (a skin adapter "
                         "needs skin windows with their taxel positions built live in the control loop, which deploy "
                         "does not do yet: docs/skin.md). Deploy its student alone (--policy student) with --skin to "
                         "record the skin and its taxel positions")
    if not specs and emulated:
        log.info("policy %s reads touch (%s from %s): starting emulated Digit 360 fingertips (--digit360 sim)",
                 name, ", ".join(policy.windows), ", ".join(policy.fingers))
        return {finger: "sim" for finger in policy.fingers}
    missing = [f for f in policy.fingers if f not in specs]
    if missing:
        given = f"--digit360 names {', '.join(specs)}" if specs else "no --digit360 was given"
        raise ValueError(f"policy {name!r} reads touch ({', '.join(policy.windows)}) from the fingertips "
                         f"{', '.join(policy.fingers)}, but {given}: name a Digit 360 for each of "
                         f"{', '.join(missing)} (e.g. --digit360 {','.join(f'{f}=SERIAL' for f in policy.fingers)})"
                         + ("" if emulated else ", or deploy the student alone (--policy student)"))
    media = media or {}
    gives = {f: digit360_windows(specs[f], emulated, media.get(f)) for f in policy.fingers}
    gaps = {f: [w for w in policy.windows if w not in gives[f]] for f in policy.fingers}
    gaps = {f: w for f, w in gaps.items() if w}
    if gaps:
        lacking = "; ".join(f"{f}={specs[f]} gives {', '.join(gives[f])}, not {', '.join(w)}" for f, w in gaps.items())
        where = "" if emulated and all(specs[f] == "sim" for f in gaps) else (
            " (a real sensor's camera and microphones are found on the USB hub of its data tty: is the whole sensor "
            "plugged in, and not only its serial port?)")
        raise ValueError(f"policy {name!r} reads the touch windows {', '.join(policy.windows)}, which its "
                         f"--digit360 sensors do not all stream ({lacking}){where}. Deploy an adapter that reads "
                         "only what the sensors give (e.g. imu, pressure), or the student alone")
    return specs


def adapter_inputs(window: Mapping[str, Any], names: tuple[str, ...], finger: str) -> dict[str, np.ndarray]:
    """One reader window (rotation.hardware.digit360.reader: image (6, 224, 224) uint8, audio (2, 27000) int16, imu
    (224, 3) g, pressure (224, 1) hPa) -> the adapter's batch-of-one inputs of the windows ``names``: image as the
    contract's float32 in [0, 1] (as the env's ``tactile`` group), audio as ``audio_wave`` int16 (the encoder's
    preprocessing runs the filterbank). TouchUnavailable naming the finger when a window is missing."""
    from adapters.bundle import TouchUnavailable

    gaps = [n for n in names if n not in window]
    if gaps:
        raise TouchUnavailable(f"digit360 {finger}: its window has no {', '.join(gaps)}")
    out: dict[str, np.ndarray] = {}
    for n in names:
        x = np.asarray(window[n])
        if n == "image":
            x = x.astype(np.float32) / np.float32(255.0)  # uint8 -> [0, 1], channel order unchanged
        out["audio_wave" if n == "audio" else n] = x[None]  # (1, ...)
    return out


def wait_for_touch(policy: Any, readers: Mapping[str, Any], timeout_s: float = WARM_UP_S,
                   poll_s: float = 0.05) -> float | None:
    """Before the motors go on: wait until every fingertip the adapter reads gives its windows, then run the encoder
    once on them (its first call allocates). Returns the wait (s), or None after ``timeout_s`` (a warning names the
    fingertips and the cause; the run then starts as the student alone until touch comes). Never raises for a
    sensor that is not ready or stalled."""
    from adapters.bundle import TouchUnavailable
    from rotation.hardware.digit360.reader import SensorStale
    from rotation.hardware.digit360.window import WindowNotReady

    names = tuple(policy.windows)
    serial_only = not {"image", "audio"} & set(names)
    start = time.monotonic()
    waiting: dict[str, str] = {}
    while True:
        windows, waiting = {}, {}
        for finger in policy.fingers:
            reader = readers.get(finger)
            if reader is None:
                waiting[finger] = "no sensor"
                continue
            try:
                windows[finger] = adapter_inputs(reader.window(serial_only=serial_only), names, finger)
            except (WindowNotReady, SensorStale, TouchUnavailable) as err:
                waiting[finger] = str(err)
        if not waiting:
            try:
                policy.tokens(windows)  # the encoder's first call (allocation) happens here, not in the run
            except TouchUnavailable as err:  # non-finite first windows: the run's refreshes decide
                log.warning("touch: the first windows gave no embeddings (%s); the run starts as the student alone "
                            "until touch is usable", err)
                return None
            return time.monotonic() - start
        if time.monotonic() - start >= timeout_s:
            break
        time.sleep(poll_s)
    log.warning("touch: no windows within %.0f s before the start (%s); the run starts as the student alone "
                "until they come", timeout_s, "; ".join(f"{f}: {why}" for f, why in waiting.items()))
    return None
