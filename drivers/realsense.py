"""Depth or colour from a RealSense D435i, IMU (and pose) from a T265 or D435i, via pyrealsense2.

pyrealsense2 is an optional extra (``pip install 'respecd[realsense]'``), imported in the
worker thread on ``start``: a profile without a RealSense loads anywhere, and a missing SDK
is a DriverUnavailableError that names the extra. The T265 needs librealsense <= 2.53.1
(support was removed in 2.54). The extra installs the current pyrealsense2 (2.59 here), and
PyPI has 2.53.1 only for x86_64 CPython <= 3.10 (no aarch64 wheel before 2.55.1), so on a
Jetson a T265 needs librealsense v2.53.1 built from source with its Python bindings. The
supported platform-motion source is the D435i's own IMU (``stream: imu``, ``product:
D435I``); with a newer SDK a T265 is not listed and the error says what to do.

The driver opens one *sensor* (not a pipeline), so the D435i's depth and colour can be two
profile entries on one device, and a mode change restarts only that sensor. Sizes and rates
come from the sensor's own stream profiles, queried on start; a request between them is
served by the next faster mode and decimated. ``frame_queue.try_wait_for_frame`` waits in the
worker thread with a timeout, so ``apply`` runs between two waits and an unplugged device is
noticed (``DriverUnavailableError``, the supervisor retries with backoff).
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Any, Literal

import structlog
from pydantic import Field, model_validator

from respecd.clock import Clock
from respecd.drivers.base import MAX_RATE_HZ, Capabilities, Decimator, DriverConfigBase, DriverContext, clamp_request
from respecd.drivers.camthread import Sample, ThreadedDriver
from respecd.drivers.realsense_modes import (
    StreamMode,
    color_to_bgr,
    depth_to_mm,
    imu_vector,
    pose_meta,
    select_motion_modes,
    select_video_mode,
    version_tuple,
    video_capabilities,
    video_modes,
)
from respecd.errors import DriverUnavailableError
from respecd.messages import Modality, SensorConfig

log = structlog.get_logger(__name__)

T265_LAST_SDK = (2, 53, 1)
STREAM_MODALITY = {"depth": "depth", "color": "rgb", "imu": "imu"}
SENSOR_STREAMS = {"depth": {"depth"}, "color": {"color"}, "imu": {"accel", "gyro", "pose"}}
INSTALL_HINT = "pip install 'respecd[realsense]'"
T265_HINT = (
    "a T265 needs librealsense <= 2.53.1 (removed in 2.54): PyPI has pyrealsense2 2.53.1 only for x86_64 "
    "CPython <= 3.10, so on a Jetson build librealsense v2.53.1 from source with -DBUILD_PYTHON_BINDINGS=ON; "
    "or use the D435i's IMU (stream: imu, product: D435I)"
)


class RealSenseConfig(DriverConfigBase):
    driver: Literal["realsense"] = "realsense"
    modality: Modality = Field("depth", description="depth for stream: depth, rgb for color, imu for imu.")
    stream: Literal["depth", "color", "imu"] = Field(
        "depth", description="depth: uint16 mm (H, W); color: BGR; imu: float32 (6,) accel+gyro, pose in meta."
    )
    serial: str | None = Field(None, description="Device serial number; the first suitable device when absent.")
    product: str | None = Field(None, description="Part of the device name to match, e.g. D435I or T265.")
    wait_timeout_ms: int = Field(200, ge=10, le=5000, description="One frame wait in the worker (ms).")
    stall_timeout_s: float = Field(5.0, gt=0, le=60, description="Seconds without a frame before the driver fails.")

    @model_validator(mode="after")
    def _modality_matches_stream(self) -> RealSenseConfig:
        if self.modality != STREAM_MODALITY[self.stream]:
            wanted = STREAM_MODALITY[self.stream]
            raise ValueError(f"stream {self.stream} produces {wanted} frames, not {self.modality}")
        return self


def import_sdk() -> Any:
    """pyrealsense2, or DriverUnavailableError naming the extra."""
    try:
        import pyrealsense2 as rs
    except ImportError as err:
        raise DriverUnavailableError(f"realsense: pyrealsense2 is not available ({err}); {INSTALL_HINT}") from err
    return rs


class RealSenseSource:
    """One RealSense sensor, driven by the worker thread."""

    def __init__(self, driver: RealSenseDriver, stop: threading.Event, device: Any = None) -> None:
        self.driver = driver
        self.cfg: RealSenseConfig = driver.config
        self.stop = stop
        self.device = device
        self.rs: Any = None
        self.sensor: Any = None
        self.queue: Any = None
        self.profiles: dict[StreamMode, Any] = {}
        self.modes: list[StreamMode] = []
        self.opened: tuple[StreamMode, ...] = ()
        self.caps: Capabilities | None = None
        self.applied: SensorConfig = driver.request
        self.decimator = Decimator(driver.request.rate_hz)
        self.depth_units = 0.001
        self.last_accel: tuple[float, float, float] | None = None
        self.last_pose: dict[str, Any] | None = None
        self.stale_frames = 0  # old-mode frames dropped after a switch

    # --- lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        self.rs = import_sdk()
        if self.device is None:
            self.device = self._find_device()
        self.sensor = self._sensor()
        self._list_modes()
        self.queue = self.rs.frame_queue(2)  # small: a fresh frame beats a complete history
        if self.cfg.stream == "depth" and self.sensor.supports(self.rs.option.depth_units):
            self.depth_units = float(self.sensor.get_option(self.rs.option.depth_units))  # metres per count
        assert self.caps is not None, "capabilities are read before the stream opens"
        self.applied = self.reconfigure(clamp_request(self.caps, self.driver.request))
        log.info("realsense_open", sensor=self.cfg.name, device=_info(self.rs, self.device), modes=len(self.modes))

    def close(self) -> None:
        if self.sensor is not None and self.opened:
            for step in (self.sensor.stop, self.sensor.close):
                try:
                    step()
                except RuntimeError:
                    pass  # already stopped, or the device is gone
        self.opened = ()

    def _find_device(self) -> Any:
        rs = self.rs
        devices = list(rs.context().query_devices())
        if self.cfg.serial:
            devices = [d for d in devices if _info(rs, d, "serial_number") == self.cfg.serial]
        if self.cfg.product:
            devices = [d for d in devices if self.cfg.product.lower() in _info(rs, d).lower()]
        devices = [d for d in devices if self._sensor_of(d) is not None]
        if devices:
            return devices[0]
        wanted = " ".join(filter(None, [self.cfg.product, self.cfg.serial])) or f"a {self.cfg.stream} device"
        hint = ""
        wants_t265 = self.cfg.product is None or "t265" in self.cfg.product.lower()
        if self.cfg.stream == "imu" and wants_t265 and version_tuple(getattr(rs, "__version__", "0")) > T265_LAST_SDK:
            hint = f"; librealsense {rs.__version__} cannot see a T265: {T265_HINT}"
        raise DriverUnavailableError(f"realsense: no RealSense found for {wanted}{hint}")

    def _sensor_of(self, device: Any) -> Any:
        """The device's sensor that offers our stream (by its profiles, which also fits software devices)."""
        wanted = SENSOR_STREAMS[self.cfg.stream]
        for sensor in device.query_sensors():
            if any(p.stream_type().name in wanted for p in sensor.get_stream_profiles()):
                return sensor
        return None

    def _sensor(self) -> Any:
        sensor = self._sensor_of(self.device)
        if sensor is None:
            raise DriverUnavailableError(f"realsense: {_info(self.rs, self.device)} has no {self.cfg.stream} sensor")
        return sensor

    def _list_modes(self) -> None:
        for profile in self.sensor.get_stream_profiles():
            stream = profile.stream_type().name
            fmt = profile.format().name
            if profile.is_video_stream_profile():
                video = profile.as_video_stream_profile()
                mode = StreamMode(stream, fmt, video.width(), video.height(), profile.fps())
            else:
                mode = StreamMode(stream, fmt, 0, 0, profile.fps())
            self.profiles.setdefault(mode, profile)
        self.modes = sorted(self.profiles)
        if self.cfg.stream == "imu":
            self.caps = Capabilities("imu", max_rate_hz=MAX_RATE_HZ)
        else:
            self.caps = video_capabilities(video_modes(self.modes, self.cfg.stream), self.driver.modality)

    # --- reconfiguration (worker thread) ---------------------------------------------------
    def reconfigure(self, applied: SensorConfig) -> SensorConfig:
        if self.cfg.stream == "imu":
            wanted, notes = tuple(select_motion_modes(self.modes)), list[str]()
        else:
            offered = video_modes(self.modes, self.cfg.stream)
            mode, notes = select_video_mode(offered, applied.resolution, applied.rate_hz)
            wanted = (mode,)
            applied = replace(applied, resolution=mode.size)
        if wanted != self.opened:
            self._restart(wanted)
        self.decimator = Decimator(applied.rate_hz)
        self.applied = replace(applied, notes=tuple(dict.fromkeys([*applied.notes, *notes])))
        return self.applied

    def _restart(self, modes: tuple[StreamMode, ...]) -> None:
        began = time.monotonic()
        self.close()
        self.sensor.open([self.profiles[m] for m in modes] if len(modes) > 1 else self.profiles[modes[0]])
        self.sensor.start(self.queue)
        self.opened = modes
        while self.queue.poll_for_frame():  # frames of the old mode still queued (up to its capacity, 2)
            self.stale_frames += 1
        names = [f"{m.stream} {m.width}x{m.height}@{m.fps}" for m in modes]
        log.info("realsense_mode", sensor=self.cfg.name, modes=names, switch_s=round(time.monotonic() - began, 3))

    # --- reading (worker thread) -----------------------------------------------------------
    def read(self) -> Sample | None:
        ok, frame = self.queue.try_wait_for_frame(self.cfg.wait_timeout_ms)
        if not ok:
            if hasattr(self.device, "is_connected") and not self.device.is_connected():
                raise DriverUnavailableError(f"realsense: {_info(self.rs, self.device)} disconnected")
            return None
        if self.cfg.stream == "imu":
            return self._motion(frame)
        if not self._current(frame):
            self.stale_frames += 1  # delivered after a mode switch, taken with the old mode
            return None
        t = self.driver.clock.now()
        if not self.applied.enabled or not self.decimator.accept(t):
            return None
        return Sample(self._pixels(frame), t, self._meta(frame))

    def _current(self, frame: Any) -> bool:
        """Whether a video frame was taken with the mode now open (size and rate of its profile)."""
        profile = frame.get_profile().as_video_stream_profile()
        mode = self.opened[0] if self.opened else None
        return mode is not None and (profile.width(), profile.height(), profile.fps()) == (
            mode.width, mode.height, mode.fps)

    def _pixels(self, frame: Any) -> Any:
        import numpy as np

        pixels = np.asanyarray(frame.get_data())
        if self.cfg.stream == "depth":
            return depth_to_mm(pixels, self.depth_units)
        return color_to_bgr(pixels, frame.get_profile().format().name)

    def _meta(self, frame: Any) -> dict[str, Any]:
        return {
            "frame_number": int(frame.get_frame_number()),
            "device_time_ms": float(frame.get_timestamp()),
            "time_domain": frame.get_frame_timestamp_domain().name,
        }

    def _motion(self, frame: Any) -> Sample | None:
        """Combine the latest accel with each gyro sample; keep the latest pose in meta."""
        stream = frame.get_profile().stream_type().name
        if stream == "pose":
            self.last_pose = pose_meta(frame.as_pose_frame().get_pose_data())
            return None
        data = frame.as_motion_frame().get_motion_data()
        if stream == "accel":
            self.last_accel = (data.x, data.y, data.z)
            return None
        t = self.driver.clock.now()
        if self.last_accel is None or not self.applied.enabled or not self.decimator.accept(t):
            return None
        meta = self._meta(frame)
        if self.last_pose is not None:
            meta["pose"] = self.last_pose
        return Sample(imu_vector(self.last_accel, (data.x, data.y, data.z)), t, meta)


def _info(rs: Any, device: Any, field: str = "name") -> str:
    info = getattr(rs.camera_info, field)
    return str(device.get_info(info)) if device.supports(info) else "?"


class RealSenseDriver(ThreadedDriver):
    """One stream of a RealSense device (depth, colour or IMU)."""

    key = "realsense"

    def __init__(
        self, config: RealSenseConfig, clock: Clock, context: DriverContext | None = None, device: Any = None
    ) -> None:
        super().__init__(config, clock, context)
        self.config: RealSenseConfig = config
        self._device = device  # injected: a pyrealsense2 device such as a software_device
        self._source: RealSenseSource | None = None
        self.request = config.initial_request()
        self._caps = Capabilities(self.modality, tuple(filter(None, [config.resolution])))  # until start
        self.applied = clamp_request(self._caps, self.request)

    @property
    def capabilities(self) -> Capabilities:
        return self._caps

    def make_source(self, stop: threading.Event) -> RealSenseSource:
        self._source = RealSenseSource(self, stop, self._device)
        return self._source

    async def start(self) -> None:
        await super().start()
        if self._source is not None and self._source.caps is not None:
            self._caps = self._source.caps
            self.applied = self._source.applied

    async def apply(self, request: SensorConfig) -> SensorConfig:
        self.request = request
        return await self.apply_through(self._source, self._caps, request)
