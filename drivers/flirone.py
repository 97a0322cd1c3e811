"""Thermal (or visible) frames from a FLIR One Pro over USB (pyusb), frame protocol in
``flirone_protocol.py``, USB seam in ``flirone_usb.py``.

The camera delivers ~8.7 frames/s whatever is asked, so the capabilities cap the rate at
``max_rate_hz`` (9 Hz): a higher request is clamped and the clamp reported; lower rates are
decimated in the worker. The sensor's native size is told by the thermal block itself
(160x120 on a One Pro / Gen 2, 80x60 on a Gen 3 / Pro LT); larger sizes such as the paper's
320x240 are upscales and reported as such. Flat-field-correction frames (shutter closed) and
the first frame after one are flagged ``meta["ffc"]`` (or dropped with ``skip_ffc``).
A USB error or unplug raises a DriverError, and the daemon's supervisor restarts the driver
with backoff; ``start`` raises DriverUnavailableError with a clear message when libusb, the
device or the permission is missing.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Any, Literal

import structlog
from pydantic import Field, model_validator

from respecd.clock import Clock
from respecd.drivers.base import Capabilities, Decimator, DriverConfigBase, DriverContext, clamp_request
from respecd.drivers.camthread import END, Sample, ThreadedDriver
from respecd.drivers.flirone_protocol import GEN3_SIZE, PRO_SIZE, FlirFrame, FrameAssembler
from respecd.drivers.flirone_usb import PyUsbTransport, RecordedTransport, Transport
from respecd.messages import Modality, Resolution, SensorConfig

log = structlog.get_logger(__name__)

DAMAGE_SUMMARY_S = 60.0  # corrupt USB data: the first damaged frame is logged, then a summary at most this often
NATIVE_RATE_HZ = 8.7  # measured FLIR One thermal rate ("regular 8-9 fps")
PAPER_THERMAL_RESOLUTIONS: tuple[Resolution, ...] = ((160, 120), (320, 240))  # the RL action set
STREAM_MODALITY = {"thermal": "thermal", "visible": "rgb"}


class FlirOneConfig(DriverConfigBase):
    driver: Literal["flirone"] = "flirone"
    modality: Modality = Field("thermal", description="thermal for stream: thermal, rgb for stream: visible.")
    rate_hz: float = Field(9.0, ge=1, le=30, description="Initial rate (Hz); the camera gives at most ~9.")
    stream: Literal["thermal", "visible"] = Field(
        "thermal", description="thermal: uint16 raw counts (H, W); visible: the JPEG camera decoded to BGR."
    )
    sensor: Literal["pro", "gen3"] = Field(
        "pro", description="Assumed layout until the first frame tells: pro = 160x120, gen3 = 80x60."
    )
    max_rate_hz: float = Field(9.0, ge=1, le=30, description="Rate cap offered to the controller (Hz).")
    skip_ffc: bool = Field(False, description="Drop flat-field-correction frames instead of flagging them.")
    line_crc: Literal["drop", "flag"] = Field(
        "drop", description="A frame with thermal lines whose VoSPI CRC fails: drop it, or pass it with "
        "meta['crc_errors'] > 0."
    )
    attach_jpeg: bool = Field(False, description="Thermal stream: also put the visible JPEG bytes in meta['jpeg'].")
    fileio_handshake: bool = Field(
        False, description="Send the Gen-3 FileIO preamble (CameraFiles.zip) before starting video."
    )
    usb_read_size: int = Field(1 << 20, ge=512, le=1 << 22, description="Bytes per bulk read on EP 0x85.")
    usb_timeout_ms: int = Field(100, ge=10, le=2000, description="Bulk read timeout (ms).")
    side_timeout_ms: int = Field(
        10, ge=1, le=100, description="Timeout of each drain of EP 0x81/0x83 after a frame read (ms)."
    )
    recording: str | None = Field(
        None, description="Play recorded EP 0x85 reads (folder of hex 1.txt, 2.txt, ... or raw .bin) instead of USB."
    )
    loop: bool = Field(True, description="Recording: start again at the end.")
    realtime: bool = Field(
        True, description="Recording: pace frames at ~8.7 Hz (false: as fast as read, timed by the camera's clock)."
    )
    stall_timeout_s: float = Field(5.0, gt=0, le=60, description="Seconds without a frame before the driver fails.")

    @model_validator(mode="after")
    def _modality_matches_stream(self) -> FlirOneConfig:
        if self.modality != STREAM_MODALITY[self.stream]:
            wanted = STREAM_MODALITY[self.stream]
            raise ValueError(f"stream {self.stream} produces {wanted} frames, not {self.modality}")
        return self


def thermal_capabilities(native: Resolution, max_rate_hz: float) -> Capabilities:
    """Native size first, then the action set's sizes; anything larger than native is an upscale."""
    sizes = list(dict.fromkeys([native, *PAPER_THERMAL_RESOLUTIONS]))
    area = native[0] * native[1]
    upscaled = tuple(r for r in sizes if r[0] * r[1] > area)
    kept = [native, *sorted((r for r in sizes if r != native and r in upscaled), key=lambda r: r[0] * r[1])]
    return Capabilities("thermal", tuple(kept), max_rate_hz=max_rate_hz, upscaled=upscaled)


class FlirSource:
    """Transport + assembler + decimation, driven by the worker thread."""

    def __init__(self, driver: FlirOneDriver, transport: Transport, stop: threading.Event) -> None:
        self.driver = driver
        self.cfg: FlirOneConfig = driver.config
        self.transport = transport
        self.stop = stop
        self.assembler = FrameAssembler()
        self.decimator = Decimator(driver.applied.rate_hz)
        self.pending: list[FlirFrame] = []
        self.after_ffc = False
        self.recovered_errors = 0
        self.crc_logged = False
        self.damage_seen = 0  # assembler damage already counted in health
        self.damage_logged = False
        self.damage_summarized = 0  # damage already in a log line
        self.summary_due = 0.0
        # a recording played as fast as read is timed by the camera's own clock (status JSON)
        self.device_timed = driver.device_timed
        self.device_anchor: tuple[float, float] | None = None  # (clock t, device t) of the first frame
        self._last_t = 0.0
        self._last_device_t = 0.0

    def open(self) -> None:
        self.transport.start()

    def close(self) -> None:
        self._summarize_damage()
        self.transport.close()

    def _count_damage(self) -> None:
        """Frames the assembler lost to bad bytes: health drops and errors; the first one logged, then summaries."""
        damage = self.assembler.damage
        new, self.damage_seen = damage - self.damage_seen, damage
        counts = self._damage_counts()
        health = self.driver.health
        health.drops += new
        health.errors += new
        health.last_error = (
            f"corrupt USB frame data: {damage} damaged frames dropped ({counts['truncated']} cut short, "
            f"{counts['lost_sync']} bad headers skipped, {counts['bad_thermal']} unreadable thermal blocks)"
        )
        now = time.monotonic()
        if not self.damage_logged:
            self.damage_logged, self.damage_summarized, self.summary_due = True, damage, now + DAMAGE_SUMMARY_S
            log.warning("flirone_stream_damaged", sensor=self.driver.name, **counts,
                        hint=f"USB data lost or corrupted (cable, hub, power); damaged frames are dropped and counted "
                        f"in health drops/errors; more of it is summarised every {DAMAGE_SUMMARY_S:g} s")
        elif now >= self.summary_due:
            self._summarize_damage()

    def _summarize_damage(self) -> None:
        """One line for the damage since the last line (every DAMAGE_SUMMARY_S at most, and at close)."""
        damage = self.assembler.damage
        if damage <= self.damage_summarized:
            return
        log.warning("flirone_stream_damage_summary", sensor=self.driver.name,
                    damaged_frames=damage - self.damage_summarized, **self._damage_counts())
        self.damage_summarized, self.summary_due = damage, time.monotonic() + DAMAGE_SUMMARY_S

    def _damage_counts(self) -> dict[str, int]:
        s = self.assembler.stats
        return {"truncated": s.truncated, "lost_sync": s.lost_sync, "bytes_skipped": s.bytes_skipped,
                "bad_thermal": s.bad_thermal, "frames": s.frames}

    def reconfigure(self, applied: SensorConfig) -> SensorConfig:
        if applied.rate_hz != self.decimator.rate_hz:
            self.decimator = Decimator(applied.rate_hz)
        return applied

    def read(self) -> Sample | object | None:
        if not self.pending:
            chunk = self.transport.read(self.cfg.usb_read_size, self.cfg.usb_timeout_ms)
            self._count_recovered_errors()
            if not chunk:
                return END if getattr(self.transport, "exhausted", False) else None
            self.pending = self.assembler.feed(chunk)
            if self.assembler.damage > self.damage_seen:
                self._count_damage()
            if not self.pending:
                return None
        return self._emit(self.pending.pop(0))

    def _count_recovered_errors(self) -> None:
        recovered = getattr(self.transport, "recovered_errors", 0)
        if recovered > self.recovered_errors:
            self.recovered_errors = recovered
            self.driver.health.error("USB bulk read error (recovered with clear_halt)")

    def _time(self, frame: FlirFrame) -> float:
        now = self.driver.clock.now()
        device_t = (frame.status or {}).get("usbNotifiedTimestamp")
        if not self.device_timed or not isinstance(device_t, (int, float)):
            return now
        if self.device_anchor is None or device_t < self._last_device_t:  # first frame, or the recording looped
            start = now if self.device_anchor is None else self._last_t + 1.0 / NATIVE_RATE_HZ
            self.device_anchor = (start, device_t)
        self._last_device_t = device_t
        self._last_t = self.device_anchor[0] + (device_t - self.device_anchor[1])
        return self._last_t

    def _emit(self, frame: FlirFrame) -> Sample | None:
        t = self._time(frame)
        self.driver.saw_layout(frame.layout)
        if frame.crc_errors and self._bad_lines(frame):
            return None
        ffc = frame.ffc or self.after_ffc  # flirone-v4l2 also drops the first frame after an FFC
        self.after_ffc = frame.ffc
        applied = self.driver.applied
        if (ffc and self.cfg.skip_ffc) or not applied.enabled or not self.decimator.accept(t):
            return None
        meta: dict[str, Any] = {
            "ffc": ffc,
            "repeat": frame.repeat,
            "layout": frame.layout,
            "status": frame.status,
            "device_time": (frame.status or {}).get("usbNotifiedTimestamp"),
            "crc_errors": frame.crc_errors,
        }
        if self.cfg.stream == "visible":
            data = _decode_jpeg(frame.jpeg)
            if data is None:
                self.driver.health.error("visible JPEG did not decode")
                return None
            self.driver.saw_visible((data.shape[1], data.shape[0]))
        else:
            data = _fit(frame.thermal, applied.resolution, meta)
            if self.cfg.attach_jpeg:
                meta["jpeg"] = frame.jpeg
        return Sample(data, t, meta)


    def _bad_lines(self, frame: FlirFrame) -> bool:
        """Log the first corrupted frame; True when the frame is to be dropped."""
        if not self.crc_logged:
            self.crc_logged = True
            log.warning("flirone_line_crc_failed", sensor=self.driver.name, lines=frame.crc_errors,
                        action=self.cfg.line_crc, hint="corrupted USB data; set line_crc: flag to keep such frames")
        if self.cfg.line_crc != "drop":
            return False
        self.driver.health.drops += 1
        return True


def _fit(image: Any, size: Resolution | None, meta: dict[str, Any]) -> Any:
    """Resize thermal counts to the applied size (bilinear; an upscale is marked in meta)."""
    height, width = image.shape
    if size is None or size == (width, height):
        return image
    import cv2  # only once frames flow: loading a profile must not import OpenCV

    meta["upscaled_from" if size[0] * size[1] > width * height else "resized_from"] = (width, height)
    return cv2.resize(image, size, interpolation=cv2.INTER_LINEAR)


def _decode_jpeg(jpeg: bytes) -> Any:
    import cv2
    import numpy as np

    return cv2.imdecode(np.frombuffer(jpeg, dtype=np.uint8), cv2.IMREAD_COLOR)


class FlirOneDriver(ThreadedDriver):
    """FLIR One Pro thermal (or visible) stream over pyusb."""

    key = "flirone"

    def __init__(
        self,
        config: FlirOneConfig,
        clock: Clock,
        context: DriverContext | None = None,
        transport: Transport | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._native: Resolution = PRO_SIZE if config.sensor == "pro" else GEN3_SIZE
        self._visible_size: Resolution | None = None
        super().__init__(config, clock, context)
        self.config: FlirOneConfig = config
        self._transport = transport  # injected: tests feed recorded reads through the same seam
        self.device_timed = bool(config.recording or transport is not None) and not config.realtime
        self.back_pressure = self.device_timed
        self._request = config.initial_request()
        self.applied = clamp_request(self.capabilities, self._request)

    @property
    def capabilities(self) -> Capabilities:
        if self.config.stream == "visible":
            sizes = (self._visible_size,) if self._visible_size else ()
            return Capabilities("rgb", sizes, max_rate_hz=self.config.max_rate_hz)
        return thermal_capabilities(self._native, self.config.max_rate_hz)

    def make_source(self, stop: threading.Event) -> FlirSource:
        transport = self._transport or self._new_transport()
        self._source = FlirSource(self, transport, stop)
        return self._source

    def _new_transport(self) -> Transport:
        cfg = self.config
        if cfg.recording:
            pace = NATIVE_RATE_HZ if cfg.realtime else None
            return RecordedTransport.from_path(cfg.recording, loop=cfg.loop, pace_hz=pace)
        return PyUsbTransport(cfg.usb_read_size, cfg.fileio_handshake, side_timeout_ms=cfg.side_timeout_ms)

    def saw_layout(self, layout: Resolution) -> None:
        """Worker thread: the first frame (or a different camera) tells the native size."""
        if self.config.stream == "visible" or layout == self._native:
            return
        with self._lock:
            log.info("flirone_layout", sensor=self.name, native=layout, assumed=self._native)
            self._native = layout
            self.applied = self._clamp(self._request)

    def saw_visible(self, size: Resolution) -> None:
        """Worker thread: the visible stream's size, known from the first decoded JPEG."""
        if size != self._visible_size:
            with self._lock:
                self._visible_size = size
                self.applied = self._clamp(self._request)

    def _clamp(self, request: SensorConfig) -> SensorConfig:
        applied = clamp_request(self.capabilities, request)
        if applied.rate_hz > NATIVE_RATE_HZ:
            applied = replace(applied, notes=(*applied.notes, f"the camera delivers ~{NATIVE_RATE_HZ:g} Hz"))
        return applied

    async def apply(self, request: SensorConfig) -> SensorConfig:
        with self._lock:
            self._request = request
            applied = self._clamp(request)
            self.applied = applied
        source = getattr(self, "_source", None)
        if self.worker is not None and source is not None:
            await self.in_worker(lambda: source.reconfigure(applied))
        return applied

