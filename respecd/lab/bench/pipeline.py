"""Pipeline: the simulated rover at 30 Hz on every sensor — sync jitter, loop lag, drops, CPU.

With ``--with-perception --with-controller`` the detector and the learning controller run
too (``--policy`` picks another): it explores, updates its Q-table and reconfigures the
sensors, as the daemon does. ``--neighbour N`` runs the measurement a second time beside N
spinning processes (respecd.lab.bench.neighbour) and gives the loaded figures beside the
unloaded ones, with their ratio: how well the loop holds its tick against a busy neighbour."""

from __future__ import annotations

import argparse
import asyncio
import os
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from respecd.argtypes import non_negative_int, positive_float

if TYPE_CHECKING:
    from respecd.config import Profile

LAG_PROBE_PERIOD_S = 0.005


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=positive_float, default=20.0, help="how long to run (default 20 s)")
    parser.add_argument("--config", default="builtin:sim-rover", help="profile to run (its sensors forced to 30 Hz)")
    parser.add_argument(
        "--with-perception", action="store_true", help="also run the detector (default: core pipeline only)"
    )
    parser.add_argument("--with-controller", action="store_true", help="also run the controller")
    parser.add_argument("--policy", default="learn", choices=("learn", "static", "heuristic", "exploit"),
                        help="the controller's policy with --with-controller (default learn: it explores, "
                        "updates its table and reconfigures the sensors)")
    parser.add_argument("--neighbour", type=non_negative_int, default=0, metavar="N",
                        help="measure again beside N processes spinning on a core each (a busy neighbour); "
                        "report both runs and their ratio (default 0: no second run)")


def bench_profile(source: str, with_perception: bool, with_controller: bool, policy: str = "learn") -> Any:
    from respecd.config import load_profile

    profile = load_profile(source)
    sensors = [s.model_copy(update={"rate_hz": 30.0}) for s in profile.sensors]
    return profile.model_copy(
        update={
            "sensors": sensors,
            "perception": profile.perception.model_copy(update={"enabled": with_perception}),
            "controller": profile.controller.model_copy(update={"enabled": with_controller, "policy": policy}),
        }
    )


async def _lag_probe(samples: list[float]) -> None:
    loop = asyncio.get_running_loop()
    while True:
        due = loop.time() + LAG_PROBE_PERIOD_S
        await asyncio.sleep(LAG_PROBE_PERIOD_S)
        samples.append(loop.time() - due)


async def timed_run(daemon: Any, seconds: float) -> tuple[list[float], list[float], float, float]:
    """Run ``daemon`` (a ``respecd.daemon.Daemon``: the session with the live daemon's chores) for
    ``seconds`` beside a loop-lag probe: (tick lateness s, probe lateness s, process CPU s, wall s)."""
    jitter: list[float] = []
    lag: list[float] = []
    daemon.session.hooks.tick.append(lambda scheduled, actual: jitter.append(actual - scheduled))
    probe = asyncio.create_task(_lag_probe(lag), name="lag-probe")
    cpu0, wall0 = time.process_time(), time.perf_counter()
    try:
        await daemon.run(duration=seconds)
    finally:
        probe.cancel()
        await asyncio.gather(probe, return_exceptions=True)
    return jitter, lag, time.process_time() - cpu0, time.perf_counter() - wall0


async def _measure(profile: Profile, seconds: float) -> dict[str, Any]:
    import tempfile
    from pathlib import Path

    from respecd.clock import MonotonicClock
    from respecd.daemon import Daemon
    from respecd.drivers.base import DriverContext
    from respecd.session import Session

    clock = MonotonicClock()
    context = DriverContext(seed=0, simulation=getattr(profile, "simulation", None))
    with tempfile.TemporaryDirectory() as state_dir:
        session = Session(profile, clock, context, state_dir=Path(state_dir))
        daemon = Daemon(session)
        jitter, lag, cpu_s, wall_s = await timed_run(daemon, seconds)
    pipeline = session.pipeline
    frames = {n: d.health.frames for n, d in pipeline.drivers.items()}
    dropped = sum(q.dropped for q in pipeline.frame_queues.values()) + pipeline.bundles.dropped
    warm = jitter[len(jitter) // 10 :]  # skip start-up ticks (imports, first renders)
    return {
        "seconds": round(wall_s, 2),
        "sync_rate_hz": round(pipeline.synchronizer.current_rate(), 1),
        "bundles": pipeline.synchronizer.bundles,
        "frames": frames,
        "sync_jitter_ms_p50": round(float(np.percentile(np.abs(warm), 50)) * 1000, 3),
        "sync_jitter_ms_p99": round(float(np.percentile(np.abs(warm), 99)) * 1000, 3),
        "loop_lag_ms_p99": round(float(np.percentile(lag[len(lag) // 10 :], 99)) * 1000, 3),
        "dropped": dropped,
        "cpu_percent": round(100.0 * cpu_s / wall_s, 1),
        "loop_scheduling": daemon.loop_scheduling,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def _beside_neighbours(profile: Profile, seconds: float, count: int) -> dict[str, Any]:
    from respecd.lab.bench.neighbour import busy_neighbours, cpu_seconds

    with busy_neighbours(count) as spinners:
        wall0 = time.perf_counter()
        figures = asyncio.run(_measure(profile, seconds))
        figures["neighbour_cores"] = round(cpu_seconds(spinners) / (time.perf_counter() - wall0), 2)
    figures["neighbour_processes"] = count
    return figures


def _ratios(alone: dict[str, Any], loaded: dict[str, Any]) -> dict[str, float | None]:
    keys = ("sync_jitter_ms_p50", "sync_jitter_ms_p99", "loop_lag_ms_p99")
    return {k: round(loaded[k] / alone[k], 2) if alone[k] else None for k in keys}


def run(args: argparse.Namespace) -> dict[str, Any]:
    policy = getattr(args, "policy", "learn")
    profile = bench_profile(args.config, args.with_perception, args.with_controller, policy)
    figures = asyncio.run(_measure(profile, args.seconds))
    neighbour = getattr(args, "neighbour", 0)
    if neighbour:
        figures["with_neighbour"] = _beside_neighbours(profile, args.seconds, neighbour)
        figures["neighbour_over_alone"] = _ratios(figures, figures["with_neighbour"])
    figures["config"] = {"profile": args.config, "perception": args.with_perception,
                         "controller": policy if args.with_controller else False}
    return figures
