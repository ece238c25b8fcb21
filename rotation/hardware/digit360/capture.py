"""A Digit 360's camera (OpenCV) and microphones (sounddevice), checked against the device's conventions when they
open, and the frames and samples they give, timed on the host's ``time.monotonic()``.

Device facts (docs/reference/hardware.md section 4): the camera is a UVC device (USB 2833:b015) that Meta's host
code opens with ``cv2.VideoCapture`` at OpenCV's defaults and asks for 1280 x 720 (its encoder node); Sparsh-X reads
it at 30 fps and takes a square crop of the fisheye image scaled to 224 x 224 (docs/reference/sparsh.md). The
microphones are a USB audio device: 2 channels, 48 kHz, int16, read with sounddevice from the ALSA device
``hw:N,0`` of the sensor's card.

Camera (:class:`CameraCapture`). A ``/dev/video*`` path on Linux opens with OpenCV's V4L2 backend, anything else
(an index, a file) with OpenCV's default. It asks for 1280 x 720 at 30 fps, reads back the width, height, rate and
FOURCC the device agreed to (:attr:`CameraCapture.format`), and takes one frame. What comes then:

- a rate the camera reports more than ``FPS_TOLERANCE`` away from 30 fps: asked once more with FOURCC MJPG (over
  USB 2, UVC cameras commonly give 1280 x 720 at 30 fps only compressed: an assumption about UVC, not a published
  fact of this camera), then refused (OSError naming the rate that was expected and the one that came). A camera
  that reports no rate (0) is accepted with a warning: its frames keep their own host times;
- a frame that is not 3-channel 8-bit (OpenCV's BGR), or whose short side is under 224 px: refused (OSError);
- any other size or aspect ratio: accepted (a warning when it is not 1280 x 720); every frame is centre-cropped to
  a square of its short side, scaled to 224 x 224 (area interpolation) and turned from BGR into RGB;
- reads that keep failing for ``first_frame_s`` after opening: refused (OSError). (One blocked read is not cut
  short: OpenCV's V4L2 backend gives up on it by itself, after the ``OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT`` seconds
  of its environment, 10 by default.)

Frames are stamped with the host time of their arrival; a camera whose reads fail later is reopened (and checked
again) every ``retry_s`` by :meth:`CameraCapture.run`, with one error line per failure streak.

Microphones (:class:`AudioCapture`). Before the stream opens the device is looked up
(``sounddevice.query_devices(device, 'input')``): a device that matches no input, or has fewer than 2 input
channels, is refused (OSError naming the device and its channel count), and so is one that cannot record 2 channels
of int16 at 48,000 Hz (``sounddevice.check_input_settings``). Blocks are timed by :class:`SampleClock`.

OpenCV and sounddevice are the ``hardware`` extra; without them opening raises ImportError (OSError for a
sounddevice without the PortAudio library) naming ``pip install 'tactile-rotation[hardware]'``. Both classes take
the module to use (``cv2=``, ``sounddevice=``): tests pass stand-ins with the same calls.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rotation.hardware.digit360.window import AUDIO_RATE, IMAGE_SIZE

log = logging.getLogger("rotation.hardware.digit360")

EXTRA = "pip install 'tactile-rotation[hardware]'"
CAMERA_SIZE = (1280, 720)
"""(width, height) asked of the camera: what Meta's encoder node asks for (docs/reference/hardware.md section 4)."""
CAMERA_FPS = 30.0
"""Frame rate of the camera in Sparsh-X (docs/reference/sparsh.md); asked of the camera."""
FPS_TOLERANCE = 0.1
"""A reported rate within this fraction of 30 fps is accepted (29.97 is; 25 and 15 are not: the image window's
two frames, 5 apart, would no longer be about 167 ms apart)."""
AUDIO_CHANNELS = 2


def fourcc_text(code: float) -> str:
    """OpenCV's CAP_PROP_FOURCC (four characters, little-endian in an int) as text, e.g. 'MJPG'; '' when unknown."""
    n = int(code) if np.isfinite(code) else 0
    text = n.to_bytes(4, "little", signed=False).decode("ascii", "replace") if 0 < n < 1 << 32 else ""
    return text if text.isprintable() else f"0x{n:08x}"


def fourcc_code(text: str) -> int:
    return int.from_bytes(text.encode("ascii"), "little")


def import_cv2() -> Any:
    try:
        import cv2
    except ImportError as err:
        raise ImportError(f"the Digit 360 camera needs OpenCV: {EXTRA} ({err})") from err
    return cv2


def import_sounddevice() -> Any:
    try:
        import sounddevice
    except ImportError as err:
        raise ImportError(f"the Digit 360 microphones need sounddevice: {EXTRA} ({err})") from err
    except OSError as err:  # sounddevice imports, but the PortAudio library it loads is missing
        raise OSError(f"the Digit 360 microphones need the PortAudio library (e.g. apt install libportaudio2) "
                      f"and {EXTRA}: {err}") from err
    return sounddevice


def square_rgb(frame: np.ndarray, cv2: Any, size: int = IMAGE_SIZE) -> np.ndarray:
    """A BGR frame (H, W, 3) -> its centre square (side min(H, W)) scaled to (size, size, 3) RGB uint8."""
    h, w = frame.shape[:2]
    s = min(h, w)
    crop = frame[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    return cv2.cvtColor(cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)


@dataclass(frozen=True)
class CameraFormat:
    """What the camera agreed to: read back from OpenCV after the request, and the first frame's shape."""

    width: int
    height: int
    fps: float
    """Rate the camera reports (0: it reports none)."""
    fourcc: str
    backend: str
    frame_shape: tuple[int, ...]


class CameraCapture:
    """One camera, opened and checked by :meth:`open` (see the module docstring), read frame by frame by
    :meth:`read` or by :meth:`run` on a reader thread.

    ``device``: a V4L2 node path (``/dev/video2``), an OpenCV index, or a video file (tests). ``cv2``: the OpenCV
    module or a stand-in (default: import OpenCV).
    """

    def __init__(self, device: int | str, name: str = "digit360", cv2: Any = None, first_frame_s: float = 2.0) -> None:
        self.device, self.name, self.first_frame_s = device, name, first_frame_s
        self._cv2 = cv2
        self._cap: Any = None
        self._first: tuple[float, np.ndarray] | None = None  # the frame open() checked, returned by the first read
        self.format: CameraFormat | None = None

    def _api(self, cv2: Any) -> int:
        path = isinstance(self.device, str) and self.device.startswith("/dev/video")
        return cv2.CAP_V4L2 if path and sys.platform.startswith("linux") else cv2.CAP_ANY

    def _refuse(self, what: str) -> OSError:
        self.close()
        return OSError(f"{self.name}: camera {self.device!r} {what}")

    def open(self) -> CameraFormat:
        """Open, ask for 1280 x 720 at 30 fps, check what came (OSError when refused); the agreed format."""
        cv2 = self._cv2 = self._cv2 if self._cv2 is not None else import_cv2()
        self.close()
        api = self._api(cv2)
        self._cap = cap = cv2.VideoCapture(self.device, api)
        if not cap.isOpened():
            raise self._refuse(f"did not open (OpenCV backend {'V4L2' if api == cv2.CAP_V4L2 else 'default'}); is "
                               "it the sensor's UVC capture node (USB 2833:b015), readable by this user (group video)?")
        fmt = self._request(cap, cv2)
        if fmt.fps > 0 and abs(fmt.fps - CAMERA_FPS) > FPS_TOLERANCE * CAMERA_FPS and fmt.fourcc != "MJPG":
            log.warning("%s: camera %s reports %.1f fps at %dx%d %s; asking for MJPG", self.name, self.device,
                        fmt.fps, fmt.width, fmt.height, fmt.fourcc or "(no FOURCC)")
            cap.set(cv2.CAP_PROP_FOURCC, fourcc_code("MJPG"))
            fmt = self._request(cap, cv2)
        if fmt.fps > 0 and abs(fmt.fps - CAMERA_FPS) > FPS_TOLERANCE * CAMERA_FPS:
            raise self._refuse(f"expected {CAMERA_FPS:.0f} fps (+-{FPS_TOLERANCE:.0%}) at "
                               f"{CAMERA_SIZE[0]}x{CAMERA_SIZE[1]}, got {fmt.fps:.1f} fps at {fmt.width}x{fmt.height} "
                               f"{fmt.fourcc or '(no FOURCC)'}")
        if fmt.fps <= 0:
            log.warning("%s: camera %s reports no frame rate; frames are timed on arrival", self.name, self.device)
        deadline = time.monotonic() + self.first_frame_s
        ok, frame = cap.read()
        while not ok and time.monotonic() < deadline:
            time.sleep(0.02)
            ok, frame = cap.read()
        if not ok or frame is None:
            raise self._refuse(f"opened but gave no frame in {self.first_frame_s:.1f} s")
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise self._refuse(f"expected 3-channel 8-bit (BGR) frames of {CAMERA_SIZE[0]}x{CAMERA_SIZE[1]}, got "
                               f"frames of shape {frame.shape} {frame.dtype} ({fmt.fourcc or 'no FOURCC'})")
        if min(frame.shape[:2]) < IMAGE_SIZE:
            raise self._refuse(f"expected frames of {CAMERA_SIZE[0]}x{CAMERA_SIZE[1]} (at least {IMAGE_SIZE} px on "
                               f"the short side), got {frame.shape[1]}x{frame.shape[0]}")
        if (frame.shape[1], frame.shape[0]) != CAMERA_SIZE:
            log.warning("%s: camera %s gives %dx%d frames, not %dx%d; each is centre-cropped to a square of its "
                        "short side", self.name, self.device, frame.shape[1], frame.shape[0], *CAMERA_SIZE)
        self.format = CameraFormat(frame.shape[1], frame.shape[0], fmt.fps, fmt.fourcc, fmt.backend, frame.shape)
        self._first = (time.monotonic(), square_rgb(frame, cv2))
        return self.format

    def _request(self, cap: Any, cv2: Any) -> CameraFormat:
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, CAMERA_SIZE[0])
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, CAMERA_SIZE[1])
        cap.set(cv2.CAP_PROP_FPS, CAMERA_FPS)
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        backend = cap.getBackendName() if hasattr(cap, "getBackendName") else ""
        return CameraFormat(int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)),
                            fps if np.isfinite(fps) else 0.0, fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)), backend, ())

    @property
    def is_open(self) -> bool:
        return self._cap is not None and bool(self._cap.isOpened())

    def read(self) -> tuple[float, np.ndarray] | None:
        """The next frame: (host ``time.monotonic()`` s at its arrival, (224, 224, 3) RGB uint8); None when the
        read failed or the camera is closed."""
        if self._first is not None:
            first, self._first = self._first, None
            return first
        if not self.is_open:
            return None
        ok, frame = self._cap.read()
        t = time.monotonic()
        if not ok or frame is None:
            return None
        return t, square_rgb(frame, self._cv2)

    def run(self, stop: threading.Event, sink: Callable[[float, np.ndarray], None], retry_s: float) -> None:
        """Read frames into ``sink(t, rgb)`` until ``stop``; a camera that fails is reopened every ``retry_s``
        (one error line per failure streak, one info line when frames are back). Closes the camera at the end."""
        failing = False
        try:
            while not stop.is_set():
                got = self.read()
                if got is None:
                    if not failing:
                        log.error("%s: camera %s gives no frame (%s); retrying every %.1f s", self.name, self.device,
                                  "read failed" if self.is_open else "closed", retry_s)
                    failing = True
                    stop.wait(retry_s)
                    if not self.is_open and not stop.is_set():
                        try:
                            self.open()
                        except OSError as err:
                            log.debug("%s: camera reopen failed: %s", self.name, err)
                    continue
                if failing:
                    log.info("%s: camera frames are back", self.name)
                    failing = False
                sink(*got)
        finally:
            self.close()

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()


class SampleClock:
    """Host times (``time.monotonic()`` s) of a sample stream delivered in blocks (audio): consecutive samples are
    1 / rate apart, anchored to the host clock at the first block. A block's arrival time jitters by milliseconds,
    so timing each block from its own arrival would overlap the previous block's times (a recording then drops the
    overlap); the anchor moves only when the arrival differs from the count by more than ``reanchor_s`` (lost
    samples, or drift between the sound card's clock and the host's), and never back past the previous sample."""

    def __init__(self, rate: float, reanchor_s: float = 0.02) -> None:
        self.rate, self.reanchor_s = float(rate), float(reanchor_s)
        self._next: float | None = None  # time of the next sample by the count

    def __call__(self, frames: int, t_arrival: float) -> np.ndarray:
        """Times (frames,) of a block whose last sample arrived at ``t_arrival``."""
        measured = t_arrival - (frames - 1) / self.rate
        first = measured if self._next is None else self._next
        if self._next is not None and abs(measured - self._next) > self.reanchor_s:
            first = max(measured, self._next - 1.0 / self.rate + 1e-6)
        t = first + np.arange(frames) / self.rate
        self._next = float(t[-1]) + 1.0 / self.rate if frames else self._next
        return t


class AudioCapture:
    """The two microphones as a sounddevice input stream (48 kHz, 2 channels, int16), checked by :meth:`open`
    (see the module docstring); each block goes to ``sink(times (n,), samples (n, 2) int16)`` from sounddevice's
    thread. ``sounddevice``: the module or a stand-in (default: import sounddevice)."""

    def __init__(self, device: int | str, sink: Callable[[np.ndarray, np.ndarray], None], name: str = "digit360",
                 sounddevice: Any = None) -> None:
        self.device, self.sink, self.name = device, sink, name
        self._sd = sounddevice
        self._stream: Any = None
        self.info: dict[str, Any] = {}
        """What ``query_devices`` said of the device (name, max_input_channels, default_samplerate, ...)."""
        self.blocks = 0
        self.problems = 0
        """Blocks that came with a status flag (input overflow: samples lost)."""

    def _refuse(self, what: str, err: BaseException | None = None) -> OSError:
        return OSError(f"{self.name}: microphones {self.device!r} {what}" + (f": {err}" if err else ""))

    def open(self) -> None:
        sd = self._sd = self._sd if self._sd is not None else import_sounddevice()
        try:
            info = dict(sd.query_devices(self.device, "input"))
        except Exception as err:  # ValueError: no (or more than one) input device matches
            raise self._refuse("did not open", err) from err
        self.info = info
        channels = int(info.get("max_input_channels", 0))
        if channels < AUDIO_CHANNELS:
            raise self._refuse(f"did not open: input device {info.get('name', '?')!r} has {channels} input "
                               f"channel(s); a Digit 360 has {AUDIO_CHANNELS} microphones (is it the sensor's ALSA "
                               "device hw:N,0?)")
        try:
            sd.check_input_settings(device=self.device, channels=AUDIO_CHANNELS, dtype="int16",
                                    samplerate=AUDIO_RATE)
        except Exception as err:  # PortAudioError: the rate or the format is not supported
            raise self._refuse(f"did not open: input device {info.get('name', '?')!r} cannot record {AUDIO_CHANNELS} "
                               f"channels of int16 at {AUDIO_RATE} Hz (default rate "
                               f"{info.get('default_samplerate', '?')} Hz)", err) from err
        clock = SampleClock(AUDIO_RATE)

        def callback(indata, frames, time_info, status) -> None:
            t = time.monotonic()
            if status:
                self.problems += 1
                log.warning("%s: audio %s", self.name, status)
            self.blocks += 1
            self.sink(clock(frames, t), indata)

        try:
            stream = sd.InputStream(samplerate=AUDIO_RATE, channels=AUDIO_CHANNELS, dtype="int16",
                                    device=self.device, callback=callback)
            stream.start()
        except Exception as err:  # PortAudioError (busy, unplugged), or ValueError
            raise self._refuse("did not open", err) from err
        self._stream = stream

    def close(self) -> None:
        stream, self._stream = self._stream, None
        if stream is not None:
            stream.stop()
            stream.close()
