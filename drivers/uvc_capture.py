"""The OpenCV side of the uvc driver: one ``cv2.VideoCapture`` owned by the worker thread.

Kept apart from ``uvc.py`` so that validating a profile never imports OpenCV.

OpenCV's V4L2 backend ignores ``CAP_PROP_READ_TIMEOUT_MSEC``: a stalled camera blocks each
read in ``select()`` for ``OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT`` seconds (default 10), a value
cap_v4l.cpp reads once per process. The driver sets it (1 s) before the first V4L2 capture
unless the environment already does. After every size change the camera's frame rate is
read back (a larger size may only come at a lower rate), and so is the pixel format.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import structlog

from respecd.clock import Clock
from respecd.drivers.base import MAX_RATE_HZ, Capabilities, Decimator, clamp_request
from respecd.drivers.camthread import END, Sample, sleep_until
from respecd.drivers.uvc import UVCConfig
from respecd.errors import DriverIOError, DriverUnavailableError
from respecd.messages import Resolution, SensorConfig

log = structlog.get_logger(__name__)

BACKENDS = {"any": cv2.CAP_ANY, "v4l2": cv2.CAP_V4L2, "ffmpeg": cv2.CAP_FFMPEG, "gstreamer": cv2.CAP_GSTREAMER}
GRAB_FAILURES_UNPLUGGED = 3  # consecutive failed grabs before we call the camera gone
V4L2_SELECT_TIMEOUT_ENV = "OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT"
V4L2_SELECT_TIMEOUT_S = 1  # whole seconds (cap_v4l.cpp reads an integer); 3 misses = unplugged


def limit_v4l2_wait() -> int:
    """Make a V4L2 read give up after a second instead of 10; the value in force (seconds)."""
    current = os.environ.setdefault(V4L2_SELECT_TIMEOUT_ENV, str(V4L2_SELECT_TIMEOUT_S))
    try:
        return int(current)
    except ValueError:
        return 10  # OpenCV would not parse it either: its default


class UVCSource:
    """The capture as the worker thread sees it (see ``BlockingSource``)."""

    def __init__(
        self, cfg: UVCConfig, clock: Clock, request: SensorConfig, stop: threading.Event,
        on_short_file: Callable[[int, int], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self.on_short_file = on_short_file  # (frames read, frames promised): a pass ended early
        self.frame_count = 0  # frames the file's header promises (0: not told)
        self.clock = clock
        self.stop = stop
        self.request = request
        self.applied = request
        self.caps: Capabilities | None = None
        self.cap: cv2.VideoCapture | None = None
        self.native: Resolution = (0, 0)
        self.target: Resolution | None = None
        self.device_fps = 0.0
        self.decimator = Decimator(request.rate_hz)
        self.enabled = request.enabled
        self.index = 0  # frames read from the file in this pass
        self.loops = 0
        self.offset = 0.0  # media seconds of the passes already played
        self.t0 = 0.0
        self.failures = 0
        self.fourcc: str | None = None  # pixel format read back from the camera
        self.rate_asked = request.rate_hz
        self.select_timeout_s: int | None = None  # V4L2 read timeout in force

    # --- lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        if self.cfg.is_file and not Path(str(self.cfg.device)).is_file():
            raise DriverUnavailableError(f"{self.cfg.name}: video file {self.cfg.device} does not exist")
        self.cap = self._open_capture()
        if self.cfg.is_file:
            self._probe_file()
        else:
            self._probe_camera()
        assert self.caps is not None
        self.applied = self.reconfigure(clamp_request(self.caps, self.request))
        self.t0 = self.clock.now()

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None

    def _open_capture(self) -> cv2.VideoCapture:
        device = self.cfg.device
        api = BACKENDS[self.cfg.backend]
        if api == cv2.CAP_ANY and self.cfg.is_v4l2:
            api = cv2.CAP_V4L2
        if api == cv2.CAP_V4L2:
            self.select_timeout_s = limit_v4l2_wait()
        cap = cv2.VideoCapture(device, api) if isinstance(device, int) else cv2.VideoCapture(str(device), api)
        if not cap.isOpened():
            cap.release()
            what = "video file" if self.cfg.is_file else "camera"
            raise DriverUnavailableError(f"{self.cfg.name}: cannot open {what} {device!r} (backend {self.cfg.backend})")
        if not self.cfg.is_file:
            if self.cfg.fourcc:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.cfg.fourcc))
                self.fourcc = _fourcc(cap.get(cv2.CAP_PROP_FOURCC))  # what the camera really took
                if self.fourcc != self.cfg.fourcc:
                    log.warning("uvc_fourcc_refused", sensor=self.cfg.name, wanted=self.cfg.fourcc, got=self.fourcc)
            if api != cv2.CAP_V4L2:  # FFmpeg/GStreamer streams honour it; V4L2 does not (see above)
                cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, self.cfg.stall_timeout_s * 1000)
        return cap

    def _probe_file(self) -> None:
        assert self.cap is not None
        fps = self.cap.get(cv2.CAP_PROP_FPS)
        self.device_fps = fps if 0 < fps <= 1000 else MAX_RATE_HZ  # some containers carry no rate
        self.native = (int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        count = self.cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self.frame_count = int(count) if 0 < count < 1e9 else 0
        # native first: it is the best a file offers (no resampling), and the default size
        offered = _unique([self.native, *sorted(map(tuple, self.cfg.resolutions), key=lambda r: -r[0] * r[1])])
        area = self.native[0] * self.native[1]
        upscaled = tuple(r for r in offered if r[0] * r[1] > area)
        rate = min(MAX_RATE_HZ, self.device_fps)
        self.caps = Capabilities("rgb", tuple(offered), max_rate_hz=rate, upscaled=upscaled)
        log.info("uvc_file", sensor=self.cfg.name, size=self.native, fps=round(self.device_fps, 3))

    def _probe_camera(self) -> None:
        """Ask the camera for each configured size and keep the ones it confirms."""
        assert self.cap is not None
        confirmed = [r for r in ((int(w), int(h)) for w, h in self.cfg.resolutions) if self._set_size(r) == r]
        self.native = self._size()
        self.cap.set(cv2.CAP_PROP_FPS, MAX_RATE_HZ)
        self.device_fps = self.cap.get(cv2.CAP_PROP_FPS) or MAX_RATE_HZ
        self.caps = Capabilities(
            "rgb", tuple(confirmed) or (self.native,), max_rate_hz=max(1.0, min(MAX_RATE_HZ, self.device_fps))
        )
        log.info("uvc_camera", sensor=self.cfg.name, sizes=self.caps.resolutions, fps=self.device_fps)

    # --- reconfiguration (worker thread) ---------------------------------------------------
    def reconfigure(self, applied: SensorConfig) -> SensorConfig:
        """Apply a clamped request; return it with the resolution really delivered and notes."""
        notes = list(applied.notes)
        self.enabled = applied.enabled
        resolution = applied.resolution or self.native
        resized = resolution != self.target
        if resized:
            resolution = self._apply_resolution(resolution, notes)
        if self.cfg.is_file and resolution != self.native:
            notes.append(f"resized from {self.native[0]}x{self.native[1]} by cv2.resize")
        if applied.rate_hz != self.rate_asked or self.target is None or (resized and not self.cfg.is_file):
            self._apply_rate(applied.rate_hz, notes)  # a new size may come at another rate: ask again
        applied = replace(applied, rate_hz=self.decimator.rate_hz)
        if self.fourcc and self.cfg.fourcc and self.fourcc != self.cfg.fourcc:
            notes.append(f"camera streams {self.fourcc}, not {self.cfg.fourcc}")
        self.target = resolution
        self.applied = replace(applied, resolution=resolution, notes=tuple(dict.fromkeys(notes)))
        return self.applied

    def _apply_resolution(self, wanted: Resolution, notes: list[str]) -> Resolution:
        if self.cfg.is_file:
            return wanted
        got = self._set_size(wanted)
        if got != wanted:  # some cameras only switch size before streaming starts: reopen
            self.close()
            self.cap = self._open_capture()
            got = self._set_size(wanted)
            self.cap.set(cv2.CAP_PROP_FPS, self.decimator.rate_hz)
        if got != wanted:
            notes.append(f"camera delivers {got[0]}x{got[1]}, not {wanted[0]}x{wanted[1]}")
        self.native = got
        return got

    def _apply_rate(self, rate: float, notes: list[str]) -> None:
        self.rate_asked = rate
        self.decimator = Decimator(rate)
        if self.cfg.is_file:
            if rate < self.device_fps - 1e-6:
                notes.append(f"file runs at {self.device_fps:g} fps, decimated to {rate:g} Hz")
            return
        assert self.cap is not None
        self.cap.set(cv2.CAP_PROP_FPS, rate)
        device = self.cap.get(cv2.CAP_PROP_FPS)
        if device and device + 0.5 < rate:  # camera rounded down: run it at full speed and decimate
            self.cap.set(cv2.CAP_PROP_FPS, MAX_RATE_HZ)
            device = self.cap.get(cv2.CAP_PROP_FPS)
        if device and device > rate + 0.5:
            notes.append(f"camera runs at {device:g} fps, decimated to {rate:g} Hz")
        elif device and device + 0.5 < rate:  # its fastest at this size and format is slower
            w, h = self._size()
            notes.append(f"camera delivers {device:g} fps at {w}x{h}")
            self.decimator = Decimator(device)
        self.device_fps = device or self.device_fps

    def _set_size(self, size: Resolution) -> Resolution:
        assert self.cap is not None
        self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
        self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
        return self._size()

    def _size(self) -> Resolution:
        assert self.cap is not None
        return (int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))

    # --- reading (worker thread) -----------------------------------------------------------
    def read(self) -> Sample | object | None:
        return self._read_file() if self.cfg.is_file else self._read_camera()

    def _read_camera(self) -> Sample | None:
        assert self.cap is not None
        if not self.cap.grab():
            self.failures += 1
            if self.failures >= GRAB_FAILURES_UNPLUGGED:
                raise DriverUnavailableError(f"{self.cfg.name}: camera {self.cfg.device!r} stopped delivering frames")
            return None
        self.failures = 0
        t = self.clock.now()
        if not self.enabled or not self.decimator.accept(t):
            return None  # grabbed, not retrieved: V4L2 converts (and decodes MJPG) only in retrieve
        return self._retrieve(t, {"source": "camera"})

    def _read_file(self) -> Sample | object | None:
        assert self.cap is not None
        if not self.cap.grab():
            self._pass_ended()
            if not self.cfg.loop:
                log.info("uvc_file_ended", sensor=self.cfg.name, file=str(self.cfg.device), frames=self.index,
                         passes=self.loops + 1)
                return END
            self._rewind()
        t = self.t0 + self.offset + self.index / self.device_fps
        self.index += 1
        if self.cfg.realtime and not sleep_until(self.clock, t, self.stop):
            return None
        if not self.enabled or not self.decimator.accept(t):
            return None
        return self._retrieve(t, {"source": "file", "loop": self.loops, "file_frame": self.index - 1})

    def _pass_ended(self) -> None:
        """A pass that ended before the frame count the container promised: a truncated file."""
        if 0 < self.index < self.frame_count and self.on_short_file is not None:
            self.on_short_file(self.index, self.frame_count)

    def _rewind(self) -> None:
        assert self.cap is not None
        if self.index == 0:
            raise DriverIOError(f"{self.cfg.name}: video file {self.cfg.device} has no readable frames")
        self.offset += self.index / self.device_fps
        self.index = 0
        self.loops += 1
        self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        if not self.cap.grab():  # some demuxers cannot seek: reopen instead
            self.close()
            self.cap = self._open_capture()
            if not self.cap.grab():
                raise DriverIOError(f"{self.cfg.name}: cannot rewind {self.cfg.device}")

    def _retrieve(self, t: float, meta: dict[str, Any]) -> Sample | None:
        assert self.cap is not None
        ok, image = self.cap.retrieve()
        if not ok or image is None:
            return None
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        height, width = image.shape[:2]
        target = self.target or (width, height)
        if (width, height) != target:
            shrink = target[0] * target[1] < width * height
            image = cv2.resize(image, target, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
            meta["resized_from"] = (width, height)
        return Sample(np.ascontiguousarray(image), t, meta)


def _fourcc(code: float) -> str:
    """CAP_PROP_FOURCC's number as its four characters ('' when the backend reports none)."""
    value = int(code)
    text = "".join(chr((value >> 8 * i) & 0xFF) for i in range(4))
    return text if value and text.isprintable() else ""


def _unique(items: list[Any]) -> list[Any]:
    return list(dict.fromkeys(items))
