"""Replay driver: serves one sensor's logged frames, counterfactually.

Any policy can be evaluated on a log recorded at full fidelity, because this driver does to
the logged stream what the real sensor would have done under the controller's settings:

* lower rate      -> frames are dropped on the ideal grid of the new rate (``Decimator``);
* lower resolution-> frames are resized (``cv2.INTER_AREA``); above the logged resolution
                     they are upscaled and ``apply`` says so in ``notes``;
* disabled        -> nothing is sent;
* radar mode      -> points beyond the new mode's maximum unambiguous range are removed and
                     radial velocities alias into the new mode's +-v_max (FMCW folding);
                     figures from TI's range/velocity-prioritized xWR68xx demo cfgs
                     (SENSORS.md 2.4 formulas: 56.25 m / 12.34 m; +-1.00 / +-3.21 m/s).

Frames carry their logged time; the driver sleeps on the injected clock until that time,
so a ``ManualClock`` replays in lockstep and a scaled clock at 1x or 2x. Radar frames whose
raw UART bytes were logged are decoded again by the live parser (``respecd.radar.parser``).
"""

from __future__ import annotations

import asyncio
import queue
import threading
from collections.abc import AsyncIterator, Iterator
from dataclasses import replace
from typing import Any, Literal

import numpy as np
import structlog
from pydantic import Field

from respecd.drivers.base import Capabilities, Decimator, DriverConfigBase, clamp_request
from respecd.drivers.base import Driver as _Driver
from respecd.errors import DriverIOError, DriverUnavailableError
from respecd.messages import Frame, RadarMode, Resolution, SensorConfig

log = structlog.get_logger(__name__)

# Resolutions the paper's action space offers per modality (best first); others come from the log.
ACTION_RESOLUTIONS: dict[str, tuple[Resolution, ...]] = {
    "rgb": ((1280, 720), (960, 540), (640, 360)),
    "thermal": ((320, 240), (160, 120)),
}


class ReplayConfig(DriverConfigBase):
    driver: Literal["replay"] = "replay"
    source: str | None = Field(None, description="Sensor name in the log (default: this sensor's name).")
    native_resolution: Resolution | None = Field(
        None, description="Resolution the log was recorded at; larger requests are upscaled and reported so."
    )
    max_rate_hz: float = Field(
        30.0, ge=1, le=30, description="Highest rate the log can serve (its recorded frame rate)."
    )
    radar_max_range_m: dict[str, float] = Field(
        {"range": 56.25, "velocity": 12.34},
        description="Maximum unambiguous range (m) per radar mode; points beyond are dropped on replay.",
    )
    radar_max_velocity_m_s: dict[str, float] = Field(
        {"range": 1.00, "velocity": 3.21},
        description="Maximum radial velocity (m/s) per radar mode; faster points alias into +-v_max.",
    )


class ReplayDriver(_Driver):
    """Serves ``context.replay`` (an opened ``SessionLog``) for one logged sensor."""

    key = "replay"
    config: ReplayConfig

    def __init__(self, config: ReplayConfig, clock: Any, context: Any = None) -> None:
        super().__init__(config, clock, context)
        self.source = config.source or config.name
        self._frames: Iterator[Frame] | None = None
        self._stopped = asyncio.Event()
        self._parser: Any = None
        self._prefetch: _Prefetch | None = None
        self.served = 0
        self.dropped_by_rate = 0
        self.applied = clamp_request(self.capabilities, config.initial_request())
        self._decimator = Decimator(self.applied.rate_hz)

    @property
    def capabilities(self) -> Capabilities:
        native = self.config.native_resolution
        modes: tuple[RadarMode, ...] = ("range", "velocity") if self.modality == "radar" else ()
        offered = list(ACTION_RESOLUTIONS.get(self.modality, ()))
        if native is not None and tuple(native) not in offered:
            offered.append(tuple(native))  # type: ignore[arg-type]
        offered.sort(key=lambda r: -r[0] * r[1])
        upscaled = tuple(r for r in offered if native is not None and r[0] * r[1] > native[0] * native[1])
        if native is None:
            offered = []
        return Capabilities(
            self.modality, tuple(offered), modes, max_rate_hz=self.config.max_rate_hz, upscaled=upscaled
        )

    async def start(self) -> None:
        log_ = getattr(self.context, "replay", None)
        if log_ is None:
            raise DriverUnavailableError(f"{self.name}: replay driver needs an opened log (DriverContext.replay)")
        if self.source not in log_.sensors:
            raise DriverUnavailableError(f"{self.name}: the log has no sensor {self.source!r}")
        self._stopped.clear()
        if self._frames is None:  # a restart resumes where the log was, it does not rewind
            self._frames = log_.frames(self.source, log_.shared_demux())
        self._prefetch = _Prefetch(self._frames, self.name)

    async def stop(self) -> None:
        self._stopped.set()
        prefetch, self._prefetch = self._prefetch, None
        if prefetch is not None:
            await asyncio.to_thread(prefetch.close)

    async def apply(self, request: SensorConfig) -> SensorConfig:
        applied = clamp_request(self.capabilities, request)
        if applied.rate_hz != self._decimator.rate_hz:
            self._decimator = Decimator(applied.rate_hz)
        self.applied = applied
        return applied

    async def frames(self) -> AsyncIterator[Frame]:
        prefetch = self._prefetch
        assert prefetch is not None, "start() first"
        while not self._stopped.is_set():
            # usually decoded already by the prefetch thread; waiting for it is executor work,
            # so a lockstep replay does not move the clock while a frame is still on its way
            logged = await asyncio.to_thread(prefetch.get)
            if logged is None:
                break
            await self.clock.sleep_until(logged.t)
            frame = self.counterfactual(logged)
            if frame is not None:
                self.served += 1
                yield frame
        if self._stopped.is_set():
            return
        log.info("replay.sensor_done", sensor=self.name, served=self.served, dropped_by_rate=self.dropped_by_rate)
        await self._stopped.wait()  # end of log: stay quiet (returning would look like a crash)

    def counterfactual(self, logged: Frame) -> Frame | None:
        """What the sensor would have sent under ``self.applied``; None when nothing."""
        cfg = self.applied
        if not cfg.enabled:
            return None
        if not self._decimator.accept(logged.t):
            self.dropped_by_rate += 1
            return None
        if self.modality == "radar":
            return self._radar(logged, cfg.mode)
        if cfg.resolution is not None and logged.data.ndim >= 2:
            return _resize(logged, cfg.resolution)
        return logged

    def _radar(self, frame: Frame, mode: RadarMode | None) -> Frame:
        points = self._reparse(frame)
        if mode is not None and points.size:
            rng = np.linalg.norm(points[:, :3], axis=1)
            points = points[rng <= self.config.radar_max_range_m.get(mode, np.inf)].copy()
            vmax = self.config.radar_max_velocity_m_s.get(mode)
            if vmax:  # FMCW Doppler folds into [-vmax, vmax)
                points[:, 3] = (points[:, 3] + vmax) % (2 * vmax) - vmax
        return replace(frame, data=points.astype(np.float32, copy=False))

    def _reparse(self, frame: Frame) -> np.ndarray:
        """Points from the raw UART bytes through the live parser, else the logged cloud."""
        raw = frame.meta.get("raw")
        if not isinstance(raw, (bytes, bytearray)):
            return frame.data
        if self._parser is None:
            from respecd.radar.parser import MmwParser

            self._parser = MmwParser()
        packets = [p for p in self._parser.feed(raw) if hasattr(p, "points")]
        return packets[-1].points if packets else frame.data


class _Prefetch:
    """Reads and decodes a sensor's next frames in a background thread, a few ahead.

    Decoding depends on the log alone, so it may run ahead of the clock; only handing a
    frame over is synchronised with the pipeline (``get`` from a worker thread).
    """

    DEPTH = 8  # frames decoded ahead: bounded memory (8 x 1280x720x3 = 22 MB at most)
    POLL_S = 0.1  # how often a blocked put/get checks for close()

    def __init__(self, frames: Iterator[Frame], name: str) -> None:
        self._frames = frames
        self._queue: queue.Queue[Frame | BaseException | None] = queue.Queue(self.DEPTH)
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"replay-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        item: Frame | BaseException | None = None
        try:
            for item in self._frames:
                if not self._offer(item):
                    return
            item = None  # end of log
        except Exception as err:  # noqa: BLE001 - a broken log reaches the driver task as its error
            item = err
        self._offer(item)

    def _offer(self, item: Frame | BaseException | None) -> bool:
        while not self._closed.is_set():
            try:
                self._queue.put(item, timeout=self.POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def get(self) -> Frame | None:
        """The next frame; None at the end of the log or once closed (blocking: worker thread)."""
        while not self._closed.is_set():
            try:
                item = self._queue.get(timeout=self.POLL_S)
            except queue.Empty:
                continue
            if isinstance(item, BaseException):
                raise DriverIOError(f"replay log unreadable: {item}") from item
            return item
        return None

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=2 * self.POLL_S + 1.0)


def _resize(frame: Frame, resolution: Resolution) -> Frame:
    import cv2

    height, width = frame.data.shape[:2]
    if (width, height) == tuple(resolution):
        return frame
    shrink = resolution[0] * resolution[1] < width * height
    data = cv2.resize(frame.data, tuple(resolution), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    meta = dict(frame.meta)
    gt = meta.get("gt")
    if gt is not None:
        meta["gt"] = _scale_boxes(gt, resolution[0] / width, resolution[1] / height)
    return replace(frame, data=data, meta=meta)


def _scale_boxes(gt: Any, sx: float, sy: float) -> Any:
    """Ground-truth boxes follow the image when it is resized: [x1, y1, x2, y2] in pixels,
    bare or as the ``box`` of a dict (the simulator's form, other keys kept)."""
    if not isinstance(gt, (list, tuple)):
        return gt
    scaled = []
    for item in gt:
        if isinstance(item, dict) and "box" in item:
            x1, y1, x2, y2 = item["box"]
            scaled.append({**item, "box": [x1 * sx, y1 * sy, x2 * sx, y2 * sy]})
        elif isinstance(item, (list, tuple)) and len(item) == 4:
            x1, y1, x2, y2 = item
            scaled.append([x1 * sx, y1 * sy, x2 * sx, y2 * sy])
        else:
            return gt  # an unknown shape: leave it alone rather than guess
    return scaled
