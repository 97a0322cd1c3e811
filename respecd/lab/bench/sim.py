"""Simulator cost: render time per frame for every modality and setting, and the event-loop lag
while five simulated sensors stream at 30 Hz.

Render times are measured with OpenCV on one thread (the brief's "one core" budget) over
``--frames`` renders per setting, cycling through the six scenarios. The streaming part
runs the ``builtin:sim-rover`` sensors at 30 Hz on the live clock for ``--seconds`` and
measures how late a 5 ms ticker wakes up (the daemon's loop-lag target is p99 < 5 ms), then
the same ticker with no sensors, which is the machine's own lag (other processes).
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from respecd.argtypes import positive_float, positive_int, seed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--frames", type=positive_int, default=60, help="renders per setting (default 60)")
    parser.add_argument("--seconds", type=positive_float, default=10.0, help="streaming test length (default 10 s)")
    parser.add_argument("--seed", type=seed, default=0, help="world seed >= 0 (default 0)")


def _percentiles(wall: list[float], cpu: list[float]) -> dict[str, float]:
    """Wall-clock median/p95 and median CPU time (the CPU figure ignores preemption by other processes)."""
    ms = np.asarray(wall) * 1e3
    return {
        "median_ms": round(float(np.median(ms)), 3),
        "p95_ms": round(float(np.percentile(ms, 95)), 3),
        "cpu_median_ms": round(float(np.median(cpu)) * 1e3, 3),
    }


def _rgb(state: Any, rng: np.random.Generator, res: tuple[int, int]) -> Any:
    from respecd.sim import render

    return render.render_rgb(state, res, 1 / 30, rng)


def _thermal(state: Any, rng: np.random.Generator, res: tuple[int, int]) -> Any:
    from respecd.sim import render

    return render.render_thermal(state, res, rng)


def _depth(state: Any, rng: np.random.Generator, res: tuple[int, int]) -> Any:
    from respecd.sim import render

    return render.render_depth(state, res, rng)


def _radar(state: Any, rng: np.random.Generator, mode: str) -> Any:
    from respecd.sim import render

    return render.render_radar(state, mode, 10.0, rng)


def render_costs(frames: int, seed: int) -> dict[str, Any]:
    """Median and p95 render time (ms) per modality and setting, OpenCV on one thread."""
    import cv2

    from respecd.sim import render
    from respecd.sim.world import SimulationConfig, World

    world = World(SimulationConfig(), seed)
    settings: dict[str, Callable[[Any, np.random.Generator], Any]] = {
        **{
            f"rgb {w}x{h}": functools.partial(_rgb, res=(w, h))
            for w, h in ((1280, 720), (960, 540), (640, 360))
        },
        **{
            f"thermal {w}x{h}": functools.partial(_thermal, res=(w, h))
            for w, h in ((160, 120), (320, 240))
        },
        **{
            f"depth {w}x{h}": functools.partial(_depth, res=(w, h))
            for w, h in ((848, 480), (640, 480), (424, 240))
        },
        **{f"radar {m}": functools.partial(_radar, mode=m) for m in ("range", "velocity")},
        "imu": lambda s, r: render.render_imu(s, r),
        "ground_truth 1280x720": lambda s, r: render.ground_truth(s, (1280, 720)),
    }
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        out = {}
        for name, fn in settings.items():
            for i in range(6):  # warm the per-scenario caches (backgrounds are built once per scenario)
                fn(world.state_at(30.0 * i + 1.0), np.random.default_rng(i))
            wall, cpu = [], []
            for k in range(frames):
                state = world.state_at(30.0 * (k % 6) + 1.0 + k / 30)
                rng = np.random.default_rng(k)
                start, start_cpu = time.perf_counter(), time.thread_time()
                fn(state, rng)
                wall.append(time.perf_counter() - start)
                cpu.append(time.thread_time() - start_cpu)
            out[name] = _percentiles(wall, cpu)
        return out
    finally:
        cv2.setNumThreads(threads)


async def _ticker(seconds: float) -> list[float]:
    """How late (s) a 5 ms sleep wakes up, over ``seconds``: the event loop's lag."""
    lags: list[float] = []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        due = time.perf_counter() + 0.005
        await asyncio.sleep(0.005)
        lags.append(time.perf_counter() - due)
    return lags


def _lag_figures(lags: list[float], prefix: str) -> dict[str, float]:
    lag_ms = np.asarray(lags) * 1e3
    return {
        f"{prefix}_p50_ms": round(float(np.percentile(lag_ms, 50)), 3),
        f"{prefix}_p99_ms": round(float(np.percentile(lag_ms, 99)), 3),
        f"{prefix}_max_ms": round(float(lag_ms.max()), 3),
    }


async def _stream(seconds: float, seed: int) -> dict[str, Any]:
    from dataclasses import replace

    from respecd.clock import MonotonicClock
    from respecd.config import load_profile
    from respecd.drivers import driver_class
    from respecd.drivers.base import DriverContext
    from respecd.drivers.sim import INLINE_BUDGET_S

    profile = load_profile()
    clock = MonotonicClock()
    context = DriverContext(seed=seed, simulation=profile.simulation)
    drivers: list[Any] = [driver_class(s.driver)(s, clock, context) for s in profile.sensors]  # SimDrivers
    counts = {d.name: 0 for d in drivers}
    lags: list[float] = []

    async def consume(driver: Any) -> None:
        async for _ in driver.frames():
            counts[driver.name] += 1

    async def ticker() -> None:
        lags.extend(await _ticker(seconds - clock.now()))

    for driver in drivers:
        await driver.start()
        await driver.apply(replace(driver.applied, rate_hz=30.0))
    tasks = [asyncio.create_task(consume(d), name=f"bench-{d.name}") for d in drivers]
    cpu0 = time.thread_time()  # the event loop's own CPU time: inline renders + driver bookkeeping
    await ticker()
    loop_cpu = time.thread_time() - cpu0
    for driver in drivers:
        await driver.stop()
    await asyncio.gather(*tasks)
    elapsed = clock.now()
    baseline = await _ticker(min(seconds, 5.0))  # the same ticker with no sensors: the machine's own lag
    return {
        "rates_hz": {name: round(n / elapsed, 2) for name, n in counts.items()},
        **_lag_figures(lags, "loop_lag"),
        **_lag_figures(baseline, "no_sensors_loop_lag"),
        "drops": {d.name: d.health.drops for d in drivers},
        "loop_cpu_ms_per_frame": round(loop_cpu / max(sum(counts.values()), 1) * 1e3, 3),
        "render_cpu_ms": {d.name: round((d.render_cost_s or 0.0) * 1e3, 3) for d in drivers},
        "inline": sorted(d.name for d in drivers if (d.render_cost_s or 1.0) < INLINE_BUDGET_S),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "render_one_thread": render_costs(args.frames, args.seed),
        "stream_5_sensors_30hz": asyncio.run(_stream(args.seconds, args.seed)),
    }
