"""Synchronizer against ROS 2 message_filters' ``ApproximateTimeSynchronizer`` on one stream.

The stream is the simulated rover's five sensors at their profile rates (RGB and IMU 30 Hz,
depth 15, radar 10, thermal 8.7), each frame a little late (|N(0, 2 ms)|), in arrival order.
Ours: every frame is put on its sensor's drop-oldest queue, and the synchronizer ticks on its
30 Hz grid (``Synchronizer.tick``, as ``run`` calls it, without the clock's sleep). Peer:
every frame goes through ``ApproximateTimeSynchronizer.add`` (queue size 10, slop = our
pairing tolerance), as its subscribers' callbacks call it. Cost = CPU time / input frames.

message_filters is a ROS 2 package, not on PyPI: the peer's module is loaded from a checkout
of ros2/message_filters (``--peers DIR``, ``DIR/message_filters/src/message_filters``). rclpy's
``Time`` and ``Duration`` wrap C handles; the stand-ins here are plain Python with the same
arithmetic, so the peer's figure is a lower bound on its cost inside ROS 2.
"""

from __future__ import annotations

import importlib.util
import sys
import time
import types
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from respecd.clock import ManualClock
from respecd.drivers.base import Driver
from respecd.messages import Bundle, Frame, SensorConfig
from respecd.queues import DropOldestQueue
from respecd.sensors import Capabilities, DriverConfigBase
from respecd.sync import Synchronizer, grid_time

RATES = {"rgb": 30.0, "imu": 30.0, "depth": 15.0, "radar": 10.0, "thermal": 8.7}
TOLERANCE_S = 0.05
QUEUE_SIZE = 10


@dataclass(frozen=True)
class Arrival:
    sensor: str
    t: float


def stream(seconds: float, seed: int = 0) -> list[Arrival]:
    """Every sensor's frames over ``seconds``, each late by |N(0, 2 ms)|, in arrival order."""
    rng = np.random.default_rng(seed)
    arrivals = []
    for sensor, rate in RATES.items():
        n = int(seconds * rate)
        stamps = np.arange(n) / rate + rng.random() / rate + np.abs(rng.normal(0.0, 0.002, n))
        arrivals += [Arrival(sensor, float(t)) for t in stamps]
    return sorted(arrivals, key=lambda a: a.t)


def ours(arrivals: list[Arrival]) -> dict[str, Any]:
    """CPU µs per input frame of our queues + synchronizer ticks over the stream."""
    drivers = {name: _driver(name, rate) for name, rate in RATES.items()}
    inputs = {name: DropOldestQueue[Frame](8) for name in drivers}
    sync = Synchronizer(drivers, inputs, DropOldestQueue[Bundle](4), ManualClock())
    rate = sync.current_rate()
    frames = [(a, Frame(a.sensor, a.t, i, None)) for i, a in enumerate(arrivals)]  # type: ignore[arg-type]
    complete = 0
    next_tick = grid_time(arrivals[0].t, rate, sync.phase)
    started = time.process_time()
    for arrival, frame in frames:
        while next_tick <= arrival.t:
            complete += len(sync.tick(next_tick, next_tick, rate).frames) == len(RATES)
            next_tick += 1.0 / rate
        inputs[arrival.sensor].put(frame)
    cpu = time.process_time() - started
    return {"us_per_input": round(cpu / len(arrivals) * 1e6, 2), "inputs": len(arrivals),
            "bundles": sync.bundles, "complete_bundles": complete}


def peer(arrivals: list[Arrival], checkout: Path) -> dict[str, Any]:
    """CPU µs per input frame of message_filters' ApproximateTimeSynchronizer over the stream."""
    module = load_message_filters(checkout)
    filters = [module.SimpleFilter() for _ in RATES]
    ats = module.ApproximateTimeSynchronizer(filters, QUEUE_SIZE, TOLERANCE_S)
    matched = []
    ats.registerCallback(lambda *msgs: matched.append(len(msgs)))
    index = {name: i for i, name in enumerate(RATES)}
    stamp_type = sys.modules["builtin_interfaces.msg"].Time
    messages = [(index[a.sensor], _Message(stamp_type(int(a.t), round((a.t % 1) * 1e9)))) for a in arrivals]
    started = time.process_time()
    for i, msg in messages:
        filters[i].signalMessage(msg)  # what the topic's subscriber does with each message
    cpu = time.process_time() - started
    return {"us_per_input": round(cpu / len(arrivals) * 1e6, 2), "inputs": len(arrivals), "matched_sets": len(matched)}


def load_message_filters(checkout: Path) -> types.ModuleType:
    """message_filters' ``__init__`` from a checkout, with rclpy's time types stood in for."""
    path = checkout / "src" / "message_filters" / "__init__.py"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not a ros2/message_filters checkout")
    _install_rclpy_stand_ins()
    spec = importlib.util.spec_from_file_location("_peer_message_filters", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class _StreamDriver(Driver):
    """Frames come from the bench's stream; only ``config`` and ``applied`` are read."""

    key = "bench-stream"

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(modality=self.modality)

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def frames(self) -> AsyncIterator[Any]:
        return
        yield

    async def apply(self, request: SensorConfig) -> SensorConfig:
        return request


def _driver(name: str, rate: float) -> _StreamDriver:
    config = DriverConfigBase(driver="bench-stream", name=name, modality=name, rate_hz=rate,
                              tolerance_ms=TOLERANCE_S * 1000)
    return _StreamDriver(config, ManualClock())


class _Message:
    __slots__ = ("header",)

    def __init__(self, stamp: Any) -> None:
        self.header = types.SimpleNamespace(stamp=stamp)


def _install_rclpy_stand_ins() -> None:
    """rclpy.time.Time / rclpy.duration.Duration / builtin_interfaces.msg.Time with rclpy's arithmetic."""
    if "rclpy" in sys.modules:
        return  # installed already, or a real rclpy: use it

    class Duration:
        __slots__ = ("nanoseconds",)

        def __init__(self, *, seconds: float = 0, nanoseconds: int = 0) -> None:
            self.nanoseconds = int(seconds * 1e9) + int(nanoseconds)

        def __lt__(self, other: Duration) -> bool:
            return self.nanoseconds < other.nanoseconds

        def __gt__(self, other: Duration) -> bool:
            return self.nanoseconds > other.nanoseconds

    class Time:
        __slots__ = ("nanoseconds", "clock_type")

        def __init__(self, *, seconds: float = 0, nanoseconds: int = 0, clock_type: int = 1) -> None:
            self.nanoseconds = int(seconds * 1e9) + int(nanoseconds)
            self.clock_type = clock_type

        @classmethod
        def from_msg(cls, msg: Any, clock_type: int = 1) -> Time:
            return cls(seconds=msg.sec, nanoseconds=msg.nanosec, clock_type=clock_type)

        def __sub__(self, other: Time) -> Duration:
            return Duration(nanoseconds=self.nanoseconds - other.nanoseconds)

        def __lt__(self, other: Time) -> bool:
            return self.nanoseconds < other.nanoseconds

        def __gt__(self, other: Time) -> bool:
            return self.nanoseconds > other.nanoseconds

    @dataclass(frozen=True)
    class StampMsg:  # builtin_interfaces/msg/Time
        sec: int
        nanosec: int

    rclpy = types.ModuleType("rclpy")
    parts: dict[str, dict[str, Any]] = {"clock": {"ROSClock": object}, "duration": {"Duration": Duration},
             "logging": {"LoggingSeverity": types.SimpleNamespace(INFO=20), "get_logger": None},
             "time": {"Time": Time}}
    for name, attributes in parts.items():
        module = types.ModuleType(f"rclpy.{name}")
        module.__dict__.update(attributes)
        setattr(rclpy, name, module)
        sys.modules[f"rclpy.{name}"] = module
    sys.modules["rclpy"] = rclpy
    interfaces, msg = types.ModuleType("builtin_interfaces"), types.ModuleType("builtin_interfaces.msg")
    msg.Time = StampMsg  # type: ignore[attr-defined]
    interfaces.msg = msg  # type: ignore[attr-defined]
    sys.modules["builtin_interfaces"] = interfaces
    sys.modules["builtin_interfaces.msg"] = msg
