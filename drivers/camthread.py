"""One worker thread per camera, so blocking device calls never run on the event loop.

OpenCV captures, pyusb handles and RealSense pipelines are not safe to drive from several
threads, so everything that touches the device (open, read, reconfigure, close) runs in the
driver's single worker thread. The loop talks to it through two narrow channels:
``Worker.call`` (run a function between two reads, get its result as a future) and a
``Handoff`` (samples out, bounded). ``ThreadedDriver`` turns that into the ``Driver``
contract: ``start``/``stop`` with timeouts, ``frames()`` that raises the worker's
``DriverError`` (the daemon's supervisor restarts the driver with backoff) and a stall
timeout, ``apply`` executed in the worker.
"""

from __future__ import annotations

import abc
import asyncio
import concurrent.futures
import queue
import threading
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
import structlog

from respecd.drivers.base import Capabilities, Driver, clamp_request
from respecd.errors import DriverError, DriverIOError, DriverTimeoutError, DriverUnavailableError
from respecd.messages import Frame, SensorConfig
from respecd.timeouts import within

log = structlog.get_logger(__name__)

T = TypeVar("T")
END = object()  # the source has no more samples (a video file that does not loop)


@dataclass(frozen=True, slots=True)
class Sample:
    """What a source read: the frame payload, its time on the driver's clock, driver facts."""

    data: np.ndarray
    t: float
    meta: dict[str, Any] = field(default_factory=dict)


class BlockingSource(Protocol):
    """A device as the worker thread sees it. Only ever called from that one thread."""

    def open(self) -> None: ...

    def read(self) -> Sample | object | None:
        """A Sample, None when nothing is due yet (timeout, decimated), or END."""
        ...

    def close(self) -> None: ...


class Handoff:
    """Bounded hand-over from the worker thread to the loop.

    ``block=True`` gives back-pressure (a video file played as fast as it is consumed);
    otherwise a full handoff drops its oldest sample (a live camera: fresh beats complete).
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, maxsize: int = 2, block: bool = False) -> None:
        self.maxsize = maxsize
        self.block = block
        self.dropped = 0
        self._loop = loop
        self._items: deque[Any] = deque()
        self._cond = threading.Condition()
        self._ready = asyncio.Event()
        self._closed = False

    def wait_for_room(self, timeout: float) -> bool:
        """Thread side, back-pressure mode: True once there is room (or the handoff is closed)."""
        with self._cond:
            if len(self._items) < self.maxsize or self._closed:
                return True
            self._cond.wait(timeout)
            return len(self._items) < self.maxsize or self._closed

    def put(self, item: Any, final: bool = False) -> None:
        """Thread side; never waits. A full handoff drops its oldest; ``final`` items are never dropped."""
        with self._cond:
            if not final and len(self._items) >= self.maxsize:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
        try:
            self._loop.call_soon_threadsafe(self._ready.set)
        except RuntimeError:  # the loop is closed: nobody is listening any more
            pass

    async def get(self, timeout: float) -> Any:
        """Loop side: the next item; raises TimeoutError after ``timeout`` seconds without one."""
        while True:
            self._ready.clear()
            with self._cond:
                if self._items:
                    item = self._items.popleft()
                    self._cond.notify()
                    return item
            await within(self._ready.wait(), timeout)

    def close(self) -> None:
        """Wake a producer blocked on a full handoff."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class Worker:
    """The thread that owns one ``BlockingSource``."""

    def __init__(self, name: str, source: BlockingSource, handoff: Handoff, stop: threading.Event) -> None:
        self.name = name
        self.source = source
        self.handoff = handoff
        self.opened: concurrent.futures.Future[None] = concurrent.futures.Future()
        self.finished: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._stop = stop
        self._commands: queue.SimpleQueue[tuple[Callable[[], Any], concurrent.futures.Future[Any]]] = (
            queue.SimpleQueue()
        )
        self._thread = threading.Thread(target=self._run, name=f"respecd-driver-{name}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.handoff.close()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def call(self, fn: Callable[[], T]) -> concurrent.futures.Future[T]:
        """Run ``fn`` in the worker between two reads."""
        future: concurrent.futures.Future[T] = concurrent.futures.Future()
        if self._stop.is_set() or self.finished.done():
            future.set_exception(DriverError(f"{self.name}: worker is not running"))
        else:
            self._commands.put((fn, future))
        return future

    def _run(self) -> None:
        try:
            self.source.open()
        except BaseException as err:  # noqa: BLE001 - handed to start(), which raises it on the loop
            self.opened.set_exception(_as_unavailable(self.name, err))
            self._close_source()
            self.finished.set_result(None)
            return
        self.opened.set_result(None)
        try:
            self._loop()
        finally:
            self._close_source()
            self._drain_commands()
            self.finished.set_result(None)

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._run_commands()
            try:
                item = self.source.read()
            except DriverError as err:
                self.handoff.put(err, final=True)
                return
            except Exception as err:  # noqa: BLE001 - vendor errors are wrapped at this boundary
                log.exception("worker_read_failed", sensor=self.name)
                self.handoff.put(DriverIOError(f"{self.name}: {type(err).__name__}: {err}"), final=True)
                return
            if item is END:
                self.handoff.put(END, final=True)
                return
            if item is not None:
                self._wait_for_room()
                self.handoff.put(item)

    def _wait_for_room(self) -> None:
        """Back-pressure: wait for the consumer, still serving ``call``s so ``apply`` cannot deadlock."""
        if not self.handoff.block:
            return
        while not self._stop.is_set() and not self.handoff.wait_for_room(0.05):
            self._run_commands()

    def _run_commands(self) -> None:
        while True:
            try:
                fn, future = self._commands.get_nowait()
            except queue.Empty:
                return
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as err:  # noqa: BLE001 - the caller on the loop re-raises it
                future.set_exception(err)

    def _drain_commands(self) -> None:
        while True:
            try:
                _, future = self._commands.get_nowait()
            except queue.Empty:
                return
            if future.set_running_or_notify_cancel():
                future.set_exception(DriverError(f"{self.name}: stopped"))

    def _close_source(self) -> None:
        try:
            self.source.close()
        except Exception:  # noqa: BLE001 - closing a gone device must not mask the real error
            log.warning("worker_close_failed", sensor=self.name, exc_info=True)


def _as_unavailable(name: str, err: BaseException) -> BaseException:
    """A vendor error while opening means "not ready, retry later"; keep it as the cause."""
    if isinstance(err, DriverError) or not isinstance(err, Exception):
        return err
    wrapped = DriverUnavailableError(f"{name}: cannot open: {type(err).__name__}: {err}")
    wrapped.__cause__ = err
    return wrapped


async def wait_future(future: concurrent.futures.Future[T], timeout: float, what: str) -> T:
    """Await a worker future; DriverTimeoutError after ``timeout`` s (the future is not cancelled)."""
    wrapped = asyncio.wrap_future(future)
    done, _ = await asyncio.wait({wrapped}, timeout=timeout)
    if not done:
        raise DriverTimeoutError(f"{what}: no answer within {timeout:g} s")
    return wrapped.result()


def sleep_until(clock: Any, t: float, stop: threading.Event, step: float = 0.005) -> bool:
    """Block the worker thread until ``clock.now() >= t``; False if the worker is stopping.

    Polls in short slices so any injected clock works, including a ManualClock moved by a test.
    """
    while (remaining := t - clock.now()) > 1e-9:  # tolerate float sums of frame periods
        if stop.wait(min(remaining, step)):
            return False
    return True


class ThreadedDriver(Driver):
    """A ``Driver`` whose device lives in one ``Worker`` thread."""

    open_timeout_s: float = 10.0
    call_timeout_s: float = 5.0
    stop_timeout_s: float = 1.5  # below the supervisor's 2 s stop budget
    back_pressure: bool = False

    _worker: Worker | None = None
    _handoff: Handoff | None = None
    _seq: int = 0
    _seen_drops: int = 0
    _ended: bool = False  # frames() saw the worker's last item

    @property
    def stall_timeout_s(self) -> float:
        return float(getattr(self.config, "stall_timeout_s", 5.0))

    @abc.abstractmethod
    def make_source(self, stop: threading.Event) -> BlockingSource:
        """A fresh device wrapper (no I/O yet), called on every start; ``stop`` is set on stop."""

    async def start(self) -> None:
        if self._worker is not None:
            if not self._ended and not self._worker.finished.done():
                return  # already running
            await self.stop()  # the stream ended (error, end of file): start afresh
        handoff = Handoff(asyncio.get_running_loop(), maxsize=2, block=self.back_pressure)
        stop = threading.Event()
        worker = Worker(self.name, self.make_source(stop), handoff, stop)
        worker.start()
        try:
            await wait_future(worker.opened, self.open_timeout_s, f"{self.name}: open")
        except BaseException as err:
            worker.stop()
            await self._join(worker)
            log.debug("driver_start_failed", sensor=self.name, error=str(err))  # the supervisor logs it once
            raise
        self._worker, self._handoff, self._seen_drops, self._ended = worker, handoff, 0, False
        self.finished = False
        log.debug("driver_started", sensor=self.name, driver=self.key)  # lifecycle is logged by the supervisor

    async def stop(self) -> None:
        worker, self._worker = self._worker, None
        if worker is None:
            return
        worker.stop()
        worker.handoff.put(END, final=True)  # wake a consumer waiting in frames()
        await self._join(worker)
        log.info("driver_stopped", sensor=self.name, frames=self.health.frames)

    async def _join(self, worker: Worker) -> None:
        try:
            await wait_future(worker.finished, self.stop_timeout_s, f"{self.name}: stop")
        except DriverTimeoutError:
            # a read stuck inside the vendor library; the daemon thread dies with the process
            log.warning("driver_stop_timeout", sensor=self.name, timeout_s=self.stop_timeout_s)
            return
        for _ in range(250):  # the thread exits right after ``finished``; let it, without blocking the loop
            if not worker.alive:
                return
            await asyncio.sleep(0.002)

    async def frames(self) -> AsyncIterator[Frame]:
        while (worker := self._worker) is not None and self._handoff is not None:
            try:
                item = await self._handoff.get(self.stall_timeout_s)
            except asyncio.TimeoutError:
                if self._worker is not worker or not self.applied.enabled:
                    continue
                self._ended = True
                raise DriverTimeoutError(f"{self.name}: no frame for {self.stall_timeout_s:g} s") from None
            if item is END or isinstance(item, BaseException):
                self._ended = True
            if item is END:
                self.finished = self._worker is worker  # the source ended by itself, not through stop()
                return
            if isinstance(item, BaseException):
                log.debug("driver_failed", sensor=self.name, error=str(item))
                raise item
            yield self._to_frame(item)

    def _to_frame(self, sample: Sample) -> Frame:
        frame = Frame(self.modality, sample.t, self._seq, sample.data, sample.meta)
        self._seq += 1
        if self._handoff is not None:  # drops since the last frame (the handoff is new each start)
            self.health.drops += self._handoff.dropped - self._seen_drops
            self._seen_drops = self._handoff.dropped
        return frame

    async def apply_through(self, source: Any, caps: Capabilities, request: SensorConfig) -> SensorConfig:
        """Clamp ``request`` and, once streaming, let ``source.reconfigure`` apply it in the worker."""
        applied = clamp_request(caps, request)
        if self.worker is not None and source is not None:
            applied = await self.in_worker(lambda: source.reconfigure(applied))
        self.applied = applied
        return applied

    async def in_worker(self, fn: Callable[[], T]) -> T:
        """Run ``fn`` in the worker thread (between reads); DriverTimeoutError if it hangs."""
        if self._worker is None:
            raise DriverError(f"{self.name}: not started")
        try:
            return await wait_future(self._worker.call(fn), self.call_timeout_s, f"{self.name}: reconfigure")
        except DriverError:
            raise
        except Exception as err:  # a vendor error during a mode switch, wrapped at the boundary
            raise DriverIOError(f"{self.name}: reconfigure failed: {type(err).__name__}: {err}") from err

    @property
    def worker(self) -> Worker | None:
        return self._worker
