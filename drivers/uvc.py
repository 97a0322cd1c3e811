"""RGB from any UVC/V4L2 camera (also the D435i's colour stream) or a video file, via OpenCV.

Resolution goes through CAP_PROP_FRAME_WIDTH/HEIGHT and is read back; a camera that will
not switch while streaming is reopened with the size set before the first read. Rate goes
through CAP_PROP_FPS where the camera takes it; the ``Decimator`` then trims to the exact
request (skipped frames are grabbed but not retrieved, so they skip OpenCV's conversion). A
video file plays at its own frame rate on the injected clock (``realtime``) or as fast as it
is consumed, loops when asked, and is resized with ``cv2.resize`` (reported in the notes).
Every OpenCV call runs in the driver's one worker thread; the capture itself lives in
``uvc_capture.py`` so that loading a profile does not import OpenCV.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Literal

import structlog
from pydantic import Field, field_validator

from respecd.clock import Clock
from respecd.drivers.base import Capabilities, DriverConfigBase, DriverContext, clamp_request
from respecd.drivers.camthread import ThreadedDriver
from respecd.messages import Modality, Resolution, SensorConfig

if TYPE_CHECKING:
    from respecd.drivers.uvc_capture import UVCSource

log = structlog.get_logger(__name__)

PAPER_RGB_RESOLUTIONS: list[Resolution] = [(1280, 720), (960, 540), (640, 360)]  # the RL action set

class UVCConfig(DriverConfigBase):
    driver: Literal["uvc"] = "uvc"
    modality: Modality = Field("rgb", description="Always rgb: frames are uint8 (H, W, 3) BGR.")
    device: int | str = Field(
        0, description="Camera index, a /dev/videoN path or udev symlink (/dev/respecd-rgb), or a video file path."
    )
    backend: Literal["any", "v4l2", "ffmpeg", "gstreamer"] = Field(
        "any", description="OpenCV capture backend; 'any' uses V4L2 for /dev paths and indices."
    )
    fourcc: str | None = Field(
        None, min_length=4, max_length=4, description="Camera pixel format, e.g. MJPG (needed for 720p30 on USB 2)."
    )
    source: Literal["auto", "camera", "file"] = Field(
        "auto",
        description="camera: a live source (a V4L2 device, or a stream URL such as rtsp://); file: a video file "
        "played on the clock; auto: an index or /dev path is a camera, a URL with :// too, anything else a file.",
    )
    loop: bool = Field(False, description="Video files: start again at the end instead of ending the stream.")
    realtime: bool = Field(
        True, description="Video files: play at the file's frame rate on the clock (false: as fast as consumed)."
    )
    resolutions: list[Resolution] = Field(
        default_factory=lambda: list(PAPER_RGB_RESOLUTIONS),
        min_length=1,
        description="Resolutions [w, h] to offer the controller; a camera keeps those it confirms on start.",
    )
    stall_timeout_s: float = Field(5.0, gt=0, le=60, description="Seconds without a frame before the driver fails.")

    @field_validator("modality")
    @classmethod
    def _rgb_only(cls, value: str) -> str:
        if value != "rgb":
            raise ValueError("the uvc driver produces rgb frames only")
        return value

    @property
    def is_v4l2(self) -> bool:
        return isinstance(self.device, int) or self.device.startswith("/dev/")

    @property
    def is_file(self) -> bool:
        if self.source != "auto":
            return self.source == "file"
        return not self.is_v4l2 and "://" not in str(self.device)


class UVCDriver(ThreadedDriver):
    """RGB frames from a UVC camera or a video file."""

    key = "uvc"

    def __init__(self, config: UVCConfig, clock: Clock, context: DriverContext | None = None) -> None:
        super().__init__(config, clock, context)
        self.config: UVCConfig = config
        self.back_pressure = config.is_file and not config.realtime
        offered = tuple((int(w), int(h)) for w, h in config.resolutions)
        self._caps = Capabilities("rgb", offered)  # until the device says more
        self._source: UVCSource | None = None
        self._short_warned = False  # a truncated file is logged once, counted in health.errors every pass
        self._request = config.initial_request()  # clamped again against what the device confirms
        self.applied = clamp_request(self._caps, self._request)

    @property
    def capabilities(self) -> Capabilities:
        return self._caps

    def make_source(self, stop: threading.Event) -> UVCSource:
        from respecd.drivers.uvc_capture import UVCSource  # OpenCV only once a camera is used

        self._source = UVCSource(self.config, self.clock, self._request, stop, on_short_file=self._short_file)
        return self._source

    def _short_file(self, reached: int, promised: int) -> None:
        """Worker thread: a video file ended before the frame count its header promises (cut short)."""
        message = f"video file {self.config.device} ended after {reached} of the {promised} frames it declares"
        self.health.error(message + " (truncated?)")
        if not self._short_warned:
            self._short_warned = True
            log.warning("uvc_file_truncated", sensor=self.name, file=str(self.config.device), frames_read=reached,
                        frames_declared=promised, hint="the file was cut short (copy or recording interrupted?)")

    async def start(self) -> None:
        await super().start()
        if self._source is not None and self._source.caps is not None:
            self._caps = self._source.caps
            self.applied = self._source.applied
            log.info("uvc_applied", sensor=self.name, rate_hz=self.applied.rate_hz, resolution=self.applied.resolution,
                     notes=self.applied.notes)

    async def apply(self, request: SensorConfig) -> SensorConfig:
        self._request = request
        return await self.apply_through(self._source, self._caps, request)

