"""Replay driver: serves one sensor's logged frames, counterfactually.

Any policy can be evaluated on a log recorded at full fidelity, because this driver does to
the logged stream what the real sensor would have done under the controller's settings:

the rules are ``respecd.replay.counterfactual``'s, shared with ``bench scenarios --log``:
the first logged frame of each period of the new rate, images resized (above the logged
resolution an upscale, said in ``notes``), radar points cut to the mode's maximum range and
velocities folded into its +-v_max (the figures of the radar driver's chirp table row for the
mode and rate), nothing when disabled.

What the controller may ask is what the robot's own driver offers (``offered``: the recorded
profile's sensor, read before the replay), never what this log happened to record: so the action
space, and a Q-table's layout, are the same for every log of one profile. A rate above what the
log recorded is applied as asked (the robot would have run it, and pays for it in the report's
energy) and served with every frame the log has, so at the recorded rate; the applied config's
notes say so, and ``unserved`` counts it for the report.

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

from respecd.drivers.base import MAX_RATE_HZ, MIN_RATE_HZ, Capabilities, DriverConfigBase, clamp_request
from respecd.drivers.base import Driver as _Driver
from respecd.errors import DriverIOError, DriverUnavailableError
from respecd.messages import Frame, RadarMode, Resolution, SensorConfig
from respecd.priority import lower_thread_priority
from respecd.replay import counterfactual
from respecd.sensors import StrictModel

log = structlog.get_logger(__name__)

# Resolutions the paper's action space offers per modality (best first); others come from the log.
ACTION_RESOLUTIONS: dict[str, tuple[Resolution, ...]] = {
    "rgb": ((1280, 720), (960, 540), (640, 360)),
    "thermal": ((320, 240), (160, 120)),
}


class Offered(StrictModel):
    """What the robot's own driver offers for a sensor (its capabilities before start, as the live
    daemon builds its action space from them)."""

    resolutions: tuple[Resolution, ...] = Field((), description="Resolutions offered, best first.")
    modes: tuple[RadarMode, ...] = Field((), description="Radar preferences offered.")
    min_rate_hz: float = Field(MIN_RATE_HZ, ge=MIN_RATE_HZ, le=MAX_RATE_HZ, description="Lowest rate offered.")
    max_rate_hz: float = Field(MAX_RATE_HZ, ge=MIN_RATE_HZ, le=MAX_RATE_HZ, description="Highest rate offered.")

    @classmethod
    def of(cls, caps: Capabilities) -> Offered:
        return cls(resolutions=caps.resolutions, modes=caps.modes, min_rate_hz=caps.min_rate_hz,
                   max_rate_hz=caps.max_rate_hz)


class ReplayConfig(DriverConfigBase):
    driver: Literal["replay"] = "replay"
    source: str | None = Field(None, description="Sensor name in the log (default: this sensor's name).")
    native_resolution: Resolution | None = Field(
        None, description="Resolution the log was recorded at; larger requests are upscaled and reported so."
    )
    max_rate_hz: float = Field(
        30.0, ge=1, le=30, description="Highest rate the log can serve (its recorded frame rate); a request above it "
        "is served at it and counted as unserved.",
    )
    empty: bool = Field(
        False, description="The log has no frame of this sensor: it serves none (the action space keeps it).",
    )
    offered: Offered | None = Field(
        None, description="What the robot's own driver offers (the controller's action space); absent: the paper's "
        "resolutions and the log's own, radar modes, 1-30 Hz.",
    )
    radar_max_range_m: dict[str, float] | None = Field(
        None, description="Maximum range (m) per radar mode, overriding the chirp table's; points beyond are dropped.",
    )
    radar_max_velocity_m_s: dict[str, float] | None = Field(
        None, description="Maximum radial velocity (m/s) per radar mode, overriding the chirp table's; "
        "faster points alias into +-v_max.",
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
        self.unserved_requests = 0  # applies asking a rate above what the log recorded
        self.unserved_asked_hz = 0.0  # the highest such rate asked
        self._unserved_s = 0.0
        self._unserved_since: float | None = None
        self.applied = self._serve(clamp_request(self.capabilities, config.initial_request()))
        self._last_logged_t: float | None = None

    @property
    def capabilities(self) -> Capabilities:
        """What the robot's driver offers (``offered``); sizes above the logged one are upscales."""
        native = self.config.native_resolution
        offered = self.config.offered
        if offered is not None:
            sizes = list(offered.resolutions)
            modes, low, high = offered.modes, offered.min_rate_hz, offered.max_rate_hz
        else:
            sizes = list(ACTION_RESOLUTIONS.get(self.modality, ())) if native is not None else []
            if native is not None and tuple(native) not in sizes:
                sizes.append(tuple(native))  # type: ignore[arg-type]
            sizes.sort(key=lambda r: -r[0] * r[1])
            modes = ("range", "velocity") if self.modality == "radar" else ()
            low, high = MIN_RATE_HZ, MAX_RATE_HZ
        upscaled = tuple(r for r in sizes if native is not None and r[0] * r[1] > native[0] * native[1])
        return Capabilities(self.modality, tuple(sizes), modes, min_rate_hz=low, max_rate_hz=high, upscaled=upscaled)

    def unserved(self, now: float) -> dict[str, float] | None:
        """What the log could not serve so far: requests, seconds under them, rates asked and recorded."""
        if not self.unserved_requests:
            return None
        seconds = self._unserved_s + (now - self._unserved_since if self._unserved_since is not None else 0.0)
        return {"requests": self.unserved_requests, "seconds": round(max(seconds, 0.0), 3),
                "asked_hz": self.unserved_asked_hz, "recorded_hz": self.config.max_rate_hz}

    def _serve(self, applied: SensorConfig) -> SensorConfig:
        """``applied`` as the robot would run it; a rate above what the log recorded is said in its notes
        and counted: the log serves every frame it has, so that sensor runs at the recorded rate."""
        recorded = self.config.max_rate_hz
        now = self.clock.now() if self.clock is not None else 0.0
        if applied.rate_hz <= recorded + 1e-9 or not applied.enabled:
            if self._unserved_since is not None:
                self._unserved_s += now - self._unserved_since
                self._unserved_since = None
            return applied
        self.unserved_requests += 1
        self.unserved_asked_hz = max(self.unserved_asked_hz, applied.rate_hz)
        if self._unserved_since is None:
            self._unserved_since = now
        note = f"rate {applied.rate_hz:g} Hz is above what the log recorded ({recorded:g} Hz): served at that"
        return replace(applied, notes=(*applied.notes, note))

    async def start(self) -> None:
        log_ = getattr(self.context, "replay", None)
        if log_ is None:
            raise DriverUnavailableError(f"{self.name}: replay driver needs an opened log (DriverContext.replay)")
        self._stopped.clear()
        if self.config.empty:
            return
        if self.source not in log_.sensors:
            raise DriverUnavailableError(f"{self.name}: the log has no sensor {self.source!r}")
        if self._frames is None:  # a restart resumes where the log was, it does not rewind
            self._frames = log_.frames(self.source, log_.shared_demux(), lazy=True)
        self._prefetch = _Prefetch(self._frames, self.name, decode=self.modality in self.context.decode_ahead)

    async def stop(self) -> None:
        self._stopped.set()
        prefetch, self._prefetch = self._prefetch, None
        if prefetch is not None:
            await asyncio.to_thread(prefetch.close)

    async def apply(self, request: SensorConfig) -> SensorConfig:
        self.applied = self._serve(clamp_request(self.capabilities, request))
        return self.applied

    async def frames(self) -> AsyncIterator[Frame]:
        if self.config.empty:  # nothing logged: stay quiet until stopped
            await self._stopped.wait()
            return
        prefetch = self._prefetch
        assert prefetch is not None, "start() first"
        while not self._stopped.is_set():
            # usually read already by the prefetch thread: taken at once, no thread hop; else
            # waiting for it is executor work, so a lockstep replay does not move the clock
            # while a frame is still on its way
            logged = prefetch.get() if prefetch.ready() else await asyncio.to_thread(prefetch.get)
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
        previous, self._last_logged_t = self._last_logged_t, logged.t
        if not cfg.enabled:
            return None
        if not counterfactual.delivers(previous, logged.t, cfg.rate_hz):
            self.dropped_by_rate += 1
            return None
        if self.modality == "radar":
            logged = replace(logged, data=self._reparse(logged))
        return counterfactual.transform(logged, cfg, self.config.radar_max_range_m, self.config.radar_max_velocity_m_s)

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
    """Reads a sensor's next frames in a background thread, a few ahead (JPEGs stay encoded
    until their pixels are read: ``respecd.record.lazy``).

    Reading depends on the log alone, so it may run ahead of the clock; only handing a frame
    over is synchronised with the pipeline (``get``: at once when ``ready``, else from a
    worker thread).
    """

    DEPTH = 16  # frames read ahead: bounded memory (JPEGs stay encoded; 16 raw 640x480 depth frames = 10 MB)
    POLL_S = 0.1  # how often a blocked put/get checks for close()

    def __init__(self, frames: Iterator[Frame], name: str, decode: bool = False) -> None:
        self._frames = frames
        self._decode = decode  # decode each frame here, off the loop (DriverContext.decode_ahead)
        self._queue: queue.Queue[Frame | BaseException | None] = queue.Queue(self.DEPTH)
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"replay-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        lower_thread_priority()
        item: Frame | BaseException | None = None
        try:
            for item in self._frames:
                if self._decode:
                    item.data  # noqa: B018 - a LazyFrame decodes on first read
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
            return self._unwrap(item)
        return None

    def ready(self) -> bool:
        """``get`` would return at once (one consumer: a queued item stays there for it)."""
        return self._closed.is_set() or not self._queue.empty()

    @staticmethod
    def _unwrap(item: Frame | BaseException | None) -> Frame | None:
        if isinstance(item, BaseException):
            raise DriverIOError(f"replay log unreadable: {item}") from item
        return item

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=2 * self.POLL_S + 1.0)
