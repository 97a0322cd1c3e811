"""TI IWR6843 mmWave radar (out-of-box demo firmware) over its two UARTs, with pyserial.

CLI port (115200): the chirp cfg, line by line, each answered ``Done``. Data port (921600):
TLV packets, read by a worker thread and parsed incrementally. The controller's action
(range/velocity preference, frame rate) maps to a chirp-table row; switching it means
``sensorStop``, ``flushCfg``, the full cfg, ``sensorStart``: the stream pauses meanwhile
(``health.paused``) and the switch time is measured and reported.

Health does not depend on what the controller does: the radar is stalled when no packet came
for ``stall_timeout_s`` (+3 frame periods) while it should stream, however many switches
happened meanwhile. A stall, a read error (unplugged board) or a reconfiguration the CLI
rejected or never answered starts one recovery: reopen the ports, send the last request (or
the last profile that streamed, if the request is what failed) from ``sensorStop`` +
``flushCfg``, and wait for packets, with exponential backoff. It is logged once when it
begins (``radar.lost``), at info level if the cause later changes kind, and once when packets
flow (``radar.back``); the per-try lines (CLI retries, cfg restarts, read errors) are debug.
Damaged data (a bad packet, garbage between packets) counts in ``health.errors`` and is a
warning the first time, then an info summary at most every ``DAMAGE_SUMMARY_S``. Frames are
counted (``health.frames``, the measured rate) by the supervisor's runner as it delivers them,
as for every driver.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import structlog
from pydantic import Field, model_validator

from respecd.clock import Clock
from respecd.drivers.base import Capabilities, Driver, DriverConfigBase, DriverContext, clamp_request
from respecd.errors import (
    ConfigError,
    DriverError,
    DriverIOError,
    DriverTimeoutError,
    DriverUnavailableError,
    InputError,
)
from respecd.messages import Frame, RadarMode, SensorConfig
from respecd.queues import DropOldestQueue
from respecd.radar import cfg
from respecd.radar.chirp import ChirpProfile, lookup, max_rate_hz
from respecd.radar.cli_port import CliPort, CliRejectedError
from respecd.radar.data_port import INTER_BYTE_TIMEOUT_S, DataPortReader
from respecd.radar.health import OutageLog
from respecd.radar.parser import MmwParser, Packet, RadarPacket
from respecd.timeouts import reap, within

log = structlog.get_logger(__name__)

MODES: tuple[RadarMode, ...] = ("range", "velocity")
DAMAGE_SUMMARY_S = 60.0  # damaged data after the first warning: one summary line at most this often
SWITCH_TIMES_KEPT = 100  # the latest reconfiguration times kept in ``switch_times_s``
_RECOVERABLE = (DriverUnavailableError, DriverIOError, DriverTimeoutError, OSError)  # SerialException is an OSError


class IWR6843Config(DriverConfigBase):
    """Profile entry for a TI IWR6843 (ISK or AOP) running the mmWave SDK 3.x out-of-box demo."""

    driver: Literal["iwr6843"] = "iwr6843"
    modality: Literal["radar"] = Field("radar", description="Always radar.")
    rate_hz: float = Field(10.0, ge=1, le=30, description="Initial frame rate (Hz); TI's presets run at 10.")
    mode: RadarMode = Field("range", description="Initial preference: range- or velocity-prioritized chirp.")
    cli_port: str = Field("/dev/respecd-radar-cli", description="CLI/config UART (udev name; ttyUSB0/ttyACM0).")
    data_port: str = Field("/dev/respecd-radar-data", description="Data UART (udev name; ttyUSB1/ttyACM1).")
    cli_baud: Literal[115200, 921600] = Field(115200, description="CLI port baud rate (the demo uses 115200).")
    data_baud: Literal[921600, 115200] = Field(921600, description="Data port baud rate (the demo uses 921600).")
    cli_timeout_s: float = Field(1.0, gt=0, le=30, description="Wait for Done per command (x4 for sensorStart).")
    cli_retries: int = Field(2, ge=0, le=10, description="Re-sends of a command that timed out or was garbled.")
    open_timeout_s: float = Field(3.0, gt=0, le=60, description="Limit for opening or closing the ports (s).")
    read_timeout_s: float = Field(0.05, gt=0, le=1, description="Data-port read granularity (s): stop latency.")
    stall_timeout_s: float = Field(3.0, gt=0, le=120, description="No packet for this long (+3 frames) = reconnect.")
    reconnect_initial_s: float = Field(0.5, gt=0, le=60, description="First reconnect delay; doubles each try.")
    reconnect_max_s: float = Field(10.0, gt=0, le=600, description="Longest reconnect delay (s).")
    base_cfg: Path | None = Field(None, description="Your own cfg: its non-chirp lines (CFAR, calibration) are kept.")
    board: Literal["isk", "aop"] = Field("isk", description="Antenna board: chirp TX order and RX gain.")
    firmware: cfg.Firmware | None = Field(
        None, description="Demo image on the board: xwr68xx_mmw_demo (ISK/ODS out-of-box, HWA+DSP, needs bpmCfg), "
        "xwr64xx_mmw_demo or xwr64xxAOP_mmw_demo (HWA only, no bpmCfg). Default: from board.")
    num_tx: Literal[2, 3] = Field(3, description="TX antennas in TDM: 3 (azimuth + elevation) or 2 (azimuth, isk).")
    range_profile: bool = Field(False, description="Also stream the range profile (TLV 2; costs UART budget).")
    max_points: int = Field(100, ge=1, le=1000,
                            description="Points per frame the frame timeline leaves UART time for (blocking write).")
    frame_queue: int = Field(4, ge=1, le=64, description="Frames buffered before the oldest is dropped.")

    @property
    def demo_firmware(self) -> cfg.Firmware:
        return self.firmware or cfg.DEFAULT_FIRMWARE[self.board]

    @model_validator(mode="after")
    def _antennas_fit_board(self) -> IWR6843Config:
        if self.num_tx == 2 and self.board != "isk":
            raise ValueError("num_tx 2 (azimuth-only TDM) is supported on board isk only")
        return self


class IWR6843Driver(Driver):
    """Radar frames as float32 (N, 5) points; ``apply`` switches the chirp profile."""

    key = "iwr6843"
    config: IWR6843Config

    def __init__(self, config: IWR6843Config, clock: Clock, context: DriverContext | None = None) -> None:
        super().__init__(config, clock, context)
        self._log = log.bind(sensor=self.name)
        self.parser = MmwParser()
        self._max_rate = min(max_rate_hz(m, *self._table_key) for m in MODES)
        self._queue: DropOldestQueue[Frame | None] = DropOldestQueue(config.frame_queue, name=self.name)
        self._cli: CliPort | None = None
        self._ports: list[Any] = []
        self._reader: DataPortReader | None = None
        self._base: list[str] | None = None
        self.profile: ChirpProfile | None = None  # what the radar runs now (None: stopped or unknown)
        self._wanted = self.applied  # the controller's latest request
        self._sent: SensorConfig | None = None  # the request whose cfg the radar accepted last
        self._good: SensorConfig | None = None  # the last request under which packets arrived
        self._suspect: SensorConfig | None = None  # a request that failed or streamed nothing
        self._rejected: dict[ChirpProfile, str] = {}  # rows the CLI refused, with its answer
        self._lock = asyncio.Lock()  # one reconfiguration (or reconnect) at a time
        self._failed = asyncio.Event()
        self._trouble: tuple[str, str] = ("stall", "no radar packets")  # (kind, message) for the watcher
        self._watch_task: asyncio.Task[None] | None = None
        self._running = False
        self._seq = 0
        self._last_packet = 0.0  # time.monotonic() of the last packet (or of the start of streaming)
        self._streaming: ChirpProfile | None = None  # the profile last started; kept while a switch runs
        self._packets_since_switch = 0
        self.outage = OutageLog(self._log)
        self.switch_times_s: deque[float] = deque(maxlen=SWITCH_TIMES_KEPT)  # oldest first
        self._damage_seen: int | None = None  # parser.stats.damaged_runs already counted (None: new connection)
        self._damage_unlogged = 0  # damaged stretches counted since the last radar.damaged_data line
        self._damage_logged_at: float | None = None  # time.monotonic() of that line (None: never logged)
        self.foreign_packets = 0
        self._stream_mode: RadarMode | None = None  # chirp preference of the frames now arriving

    @property
    def _table_key(self) -> tuple[int, int, bool]:
        return (self.config.num_tx, self.config.max_points, self.config.range_profile)

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(modality="radar", modes=MODES, min_rate_hz=1.0, max_rate_hz=float(self._max_rate))

    async def start(self) -> None:
        if self._running:
            return
        if self.config.base_cfg is not None and self._base is None:
            try:
                self._base = await asyncio.to_thread(cfg.read_cfg, self.config.base_cfg)
            except InputError as err:
                raise ConfigError(f"sensor {self.name}: base_cfg: {err}") from err
        while len(self._queue):  # the end marker of a previous stop must not end the new stream
            self._queue.get_nowait()
        async with self._lock:
            try:
                await self._connect()
                self.applied = await self._switch(self._wanted)
            except BaseException:
                await self._disconnect()
                raise
        self._running = True
        self._watch_task = asyncio.create_task(self._watch(), name=f"{self.name}-watch")
        self._log.info("radar.started", cli=self.config.cli_port, data=self.config.data_port,
                       firmware=self.config.demo_firmware)

    async def stop(self) -> None:
        if not self._running and not self._ports:
            self._queue.put(None)
            return
        self._running = False
        if self._watch_task is not None:
            await reap(self._watch_task)
            self._watch_task = None
        async with self._lock:
            if self._cli is not None and self.profile is not None:
                with contextlib.suppress(*_RECOVERABLE, TimeoutError):
                    await self._cli_call(self._cli.command, "sensorStop")
            await self._disconnect()
        self._queue.put(None)  # ends frames()
        self._log.info("radar.stopped", frames=self.health.frames, **self.parser.stats.as_dict())

    async def frames(self) -> AsyncIterator[Frame]:
        while True:
            frame = await self._queue.get()
            if frame is None:
                return
            yield frame

    async def apply(self, request: SensorConfig) -> SensorConfig:
        async with self._lock:
            planned, profile = self._plan(request)
            if profile is not None and profile in self._rejected:
                note = f"{profile.preference} at {profile.rate_hz:g} Hz was rejected ({self._rejected[profile]})"
                return replace(self.applied, notes=(*self.applied.notes, note))
            self._wanted = request
            if not self._running:
                self.applied = planned  # sent to the radar at start
                return self.applied
            try:
                self.applied = await self._switch(request)
            except DriverError as err:
                if isinstance(err, CliRejectedError) and profile is not None:
                    self._rejected[profile] = str(err)  # the demo's answer will not change: do not retry it
                self._suspect = request  # recover to the last good profile, not to this one
                self._raise_trouble(type(err).__name__, str(err))
                raise DriverIOError(f"radar {self.name}: reconfiguration failed ({err}); "
                                    "restoring the last good profile") from err
            return self.applied

    def _plan(self, request: SensorConfig) -> tuple[SensorConfig, ChirpProfile | None]:
        """Clamp to the capabilities and pick the table row; notes say what changed."""
        clamped = clamp_request(self.capabilities, request)
        if not clamped.enabled:
            return clamped, None
        profile = lookup(clamped.mode or "range", clamped.rate_hz, *self._table_key)
        notes = list(clamped.notes)
        if profile.rate_hz != clamped.rate_hz:
            notes.append(f"rate {clamped.rate_hz:g} Hz -> {profile.rate_hz:g} Hz (chirp table row)")
        return replace(clamped, rate_hz=profile.rate_hz, notes=tuple(notes)), profile

    async def _switch(self, request: SensorConfig, force: bool = False) -> SensorConfig:
        """Send the cfg for ``request`` unless the radar already runs it. Caller holds the lock."""
        planned, profile = self._plan(request)
        if self._cli is None:  # between reconnect attempts: the reconnect sends ``_wanted``
            return replace(planned, notes=(*planned.notes, "radar disconnected: applied when it is back"))
        if profile == self.profile and not force:
            return planned
        c = self.config
        lines = ["sensorStop"] if profile is None else cfg.render(profile, c.board, self._base, c.demo_firmware)
        resumes = self.profile is None  # streaming (re)starts: the stall clock starts now, not at a switch
        self.health.paused = True
        self.profile = None  # unknown until sensorStart is answered
        started = time.monotonic()
        try:
            await self._send(lines, profile)
        except asyncio.CancelledError:  # the caller gave up mid-switch: the radar's state is unknown
            self._raise_trouble("CancelledError", "reconfiguration cancelled midway")
            raise
        except DriverError as err:
            self.health.error(err)
            raise
        except (OSError, TimeoutError) as err:
            self.health.error(err)
            raise DriverTimeoutError(f"radar {self.name}: CLI call failed: {err!r}") from err
        seconds = time.monotonic() - started
        self.profile, self._sent, self._streaming = profile, request, profile
        if profile is None:
            self._log.info("radar.disabled", switch_ms=round(seconds * 1000, 1))
            return replace(planned, notes=(*planned.notes, "radar stopped (sensorStop)"))
        if resumes:
            self._last_packet = time.monotonic()
        self._packets_since_switch = 0
        self.health.paused = False
        self.switch_times_s.append(seconds)
        self._log.info("radar.switch", mode=profile.preference, rate_hz=profile.rate_hz,
                       switch_ms=round(seconds * 1000, 1), commands=len(lines), **profile.figures())
        note = f"radar reconfigured in {seconds * 1000:.0f} ms (stream paused)"
        return replace(planned, notes=(*planned.notes, note))

    async def _send(self, lines: list[str], profile: ChirpProfile | None) -> None:
        """The whole cfg; a line that times out restarts it from sensorStop + flushCfg (no duplicates)."""
        assert self._cli is not None
        for attempt in range(1, self.config.cli_retries + 2):
            try:
                await self._cli_call(self._cli.send_config, lines[:-1], lines=len(lines))
                if profile is not None:  # frames after sensorStart are the new profile's; older ones have arrived
                    self.parser.doppler_resolution = profile.velocity_resolution_mps  # SDK 2.x bins -> m/s
                    self._stream_mode = profile.preference
                await self._cli_call(self._cli.command, lines[-1])
                return
            except (DriverTimeoutError, TimeoutError) as err:
                if attempt > self.config.cli_retries:
                    raise
                # debug: a CLI that stays silent is one outage (radar.lost / the supervisor's line), not a line per try
                self._log.debug("radar.cfg_restart", attempt=attempt, error=str(err))

    async def _cli_call(self, fn: Any, *args: Any, lines: int = 1) -> Any:
        """Run a blocking CLI call in a worker thread, bounded by the per-line timeouts."""
        per_line = self.config.cli_timeout_s * 4 * (self.config.cli_retries + 1)  # x4: sensorStart is slow
        return await within(asyncio.to_thread(fn, *args), per_line * lines + 1.0)

    async def _connect(self) -> None:
        """Open both ports, wake the CLI, start the data reader. DriverUnavailableError if absent."""
        for port in (self.config.cli_port, self.config.data_port):
            if not os.path.exists(port):
                raise DriverUnavailableError(f"radar {self.name}: {port} is absent (board unplugged?)")
        opening = asyncio.ensure_future(asyncio.to_thread(self._open_ports))
        try:
            self._ports = await within(asyncio.shield(opening), self.config.open_timeout_s)
        except BaseException as err:  # timeout or cancel: close the ports if the open completes later
            opening.add_done_callback(_close_opened)
            if isinstance(err, (OSError, TimeoutError)):
                raise DriverUnavailableError(f"radar {self.name}: cannot open ports: {err}") from err
            raise
        try:
            self._cli = CliPort(self._ports[0], self.config.cli_timeout_s, self.config.cli_retries)
            await self._cli_call(self._cli.wake)
        except (OSError, TimeoutError) as err:
            raise DriverUnavailableError(f"radar {self.name}: CLI port does not answer: {err}") from err
        self._failed.clear()
        self._damage_seen = None  # bytes before this connection's first packet: the stream joined midway
        self._reader = DataPortReader(self._ports[1], self.parser, asyncio.get_running_loop(),
                                      self._on_packets, self._on_read_error, name=f"{self.name}-data")
        self._reader.start()

    def _open_ports(self) -> list[Any]:
        import serial  # pyserial: imported when a radar is really opened

        c = self.config
        cli = serial.Serial(c.cli_port, c.cli_baud, timeout=0.1, write_timeout=c.cli_timeout_s)
        try:
            data = serial.Serial(c.data_port, c.data_baud, timeout=c.read_timeout_s,
                                 inter_byte_timeout=INTER_BYTE_TIMEOUT_S)
        except BaseException:
            cli.close()
            raise
        data.reset_input_buffer()  # bytes from before we listened are a partial frame at best
        return [cli, data]

    async def _disconnect(self) -> None:
        reader, ports = self._reader, self._ports
        self._reader, self._ports, self._cli, self.profile = None, [], None, None
        if reader is not None:
            await asyncio.to_thread(reader.stop, self.config.open_timeout_s)
        for port in ports:
            with contextlib.suppress(OSError, TimeoutError):
                await within(asyncio.to_thread(port.close), self.config.open_timeout_s)

    def _on_packets(self, packets: list[Packet]) -> None:
        """On the loop: packets from the reader thread become Frames."""
        self._count_damage()
        for packet in packets:
            if not isinstance(packet, RadarPacket):
                if self.foreign_packets == 0:
                    self._log.warning("radar.foreign_format", kind=packet.kind, hint="not the out-of-box demo")
                self.foreign_packets += 1
                self._last_packet = time.monotonic()  # alive, just the wrong firmware: no reconnect churn
                self._packets_since_switch += 1
                continue
            if self._seq == 0:
                self._log.info("radar.firmware", sdk=packet.version_str, platform=f"{packet.platform:#x}")
            t = self.clock.now()
            frame = packet.to_frame(t, self._seq)
            frame.meta["mode"] = self._stream_mode
            self._seq += 1  # counted in health (frames, rate) by the supervisor's runner as it delivers it
            self.health.drops += packet.gap  # frames the radar numbered but the UART lost
            if not self._queue.put(frame):
                self.health.drops += 1
            self._last_packet = time.monotonic()
            self._packets_since_switch += 1
            if self._sent is not None and not self.health.paused:
                self._good = self._sent

    def _count_damage(self) -> None:
        """Damaged stretches of the stream (a bad packet, garbage between packets) are health errors.

        The first is a warning; later ones are summed into one info line at most every
        ``DAMAGE_SUMMARY_S`` (``_log_damage``); the totals also end up in ``radar.stopped``.
        """
        stats = self.parser.stats
        runs = stats.damaged_runs
        if self._damage_seen is None:  # a connection's leading partial packet is not damage
            self._damage_seen = runs
            return
        new = runs - self._damage_seen
        if new <= 0:
            return
        self._damage_seen = runs
        self.health.errors += new
        self.health.last_error = f"damaged radar data: {stats.last_error or 'bytes outside any packet'}"
        if self._damage_logged_at is not None:
            self._damage_unlogged += new
            return
        self._damage_logged_at = time.monotonic()
        self._log.warning("radar.damaged_data", damaged=new, error=self.health.last_error,
                          bad_packets=stats.bad_packets, bytes_skipped=stats.bytes_skipped,
                          hint="bytes lost or garbled on the data UART (cable, baud rate, port shared?)")

    def _log_damage(self) -> None:
        """The damage since the last radar.damaged_data line, once ``DAMAGE_SUMMARY_S`` has passed."""
        if not self._damage_unlogged or self._damage_logged_at is None:
            return
        since = time.monotonic() - self._damage_logged_at
        if since < DAMAGE_SUMMARY_S:
            return
        stats = self.parser.stats
        self._log.info("radar.damaged_data", damaged=self._damage_unlogged, over_s=round(since, 1),
                       error=self.health.last_error, bad_packets=stats.bad_packets, bytes_skipped=stats.bytes_skipped)
        self._damage_unlogged, self._damage_logged_at = 0, time.monotonic()

    def _on_read_error(self, err: BaseException) -> None:
        self.health.error(err)
        self._raise_trouble(type(err).__name__, f"data port read failed: {err}")

    def _raise_trouble(self, kind: str, message: str) -> None:
        self._trouble = (kind, message)
        self._failed.set()

    def _stall_limit_s(self, profile: ChirpProfile | None = None) -> float:
        profile = profile or self.profile
        period = profile.frame_period_ms / 1000 if profile is not None else 1.0
        return self.config.stall_timeout_s + 3 * period

    def _stalled(self) -> bool:
        """No packet for the limit while the radar should stream, whatever the controller did meanwhile.

        A switch in progress does not stop this clock: a controller that switches in step with
        the watcher's polls would otherwise hide a stall for ever (seen on a quiet machine:
        switches every 0.25 s, each check landing inside one).
        """
        if self._streaming is None:
            return False
        return time.monotonic() - self._last_packet > self._stall_limit_s(self._streaming)

    async def _watch(self) -> None:
        """Recover when the data port fails, goes silent, or a reconfiguration failed."""
        while self._running:
            try:
                await within(self._failed.wait(), 0.25)
            except TimeoutError:
                self._log_damage()
                if not self._stalled():
                    continue
                self._raise_trouble("stall", f"no radar packets for {time.monotonic() - self._last_packet:.1f} s")
                if self._packets_since_switch == 0 and self._sent is not None:
                    self._suspect = self._sent  # this profile never streamed: do not insist on it
            self._failed.clear()
            await self._recover()

    def _target(self) -> SensorConfig:
        """What recovery sends: the latest request, unless that one is what failed."""
        if self._wanted == self._suspect and self._good is not None:
            return self._good
        return self._wanted

    async def _recover(self) -> None:
        """Reopen, reconfigure, and wait for packets, with backoff; log once per change of cause."""
        delay = self.config.reconnect_initial_s
        self.health.paused = True
        kind, message = self._trouble
        self.health.error(message)
        self.outage.trouble(kind, message, retry_in_s=0.0)  # the first attempt is now
        while self._running:
            idle = False  # connected with the radar disabled on purpose: nothing to wait for
            async with self._lock:
                await self._disconnect()
                try:
                    await self._connect()
                    target = self._target()
                    self.applied = await self._switch(target, force=True)
                    kind, message = "stall", "configured, but no radar packets"
                    idle = not target.enabled
                except _RECOVERABLE as err:
                    kind, message = type(err).__name__, str(err)
            if idle or self.profile is not None and await self._packets_within(self._stall_limit_s()):
                self.health.restarts += 1
                self._suspect = None
                self.outage.back(restarts=self.health.restarts, mode=self.applied.mode, rate_hz=self.applied.rate_hz)
                return
            self.health.error(message)
            self.outage.trouble(kind, message, retry_in_s=delay)
            await asyncio.sleep(delay)
            delay = min(delay * 2, self.config.reconnect_max_s)

    async def _packets_within(self, seconds: float) -> bool:
        """Whether a packet arrives (or already arrived since the switch) within ``seconds``."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not self._failed.is_set():
            if self._packets_since_switch > 0:
                return True
            await asyncio.sleep(0.02)
        return self._packets_since_switch > 0


def _close_opened(opening: asyncio.Future[list[Any]]) -> None:
    """Close ports whose open finished after we stopped waiting for it."""
    if opening.cancelled() or opening.exception() is not None:
        return
    for port in opening.result():
        with contextlib.suppress(OSError):
            port.close()  # serial close of a just-opened port: no I/O to wait for
