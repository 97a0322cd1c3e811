"""Soak: the whole simulated rover for N minutes — RSS, threads, fds, queue depths, drops.

Ten minutes cannot tell warm-up (allocator pools, caches, the Q-table filling in) from a
leak, so the figure that matters is the least-squares RSS slope over the samples after
``--warmup-min``, in MB/h, with its standard error; 2-minute medians at the start and end
of that span say the same in plain numbers. RSS cannot tell a leak from freed memory the C
allocator keeps, so the C heap's bytes in use and free-but-held are sampled too. Threads and
fds must be flat; queue depths bounded by their sizes; drops are reported as totals and per hour.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from respecd.argtypes import non_negative_float, positive_float
from respecd.heap import heap_mb
from respecd.outputs import check_output_dir

if TYPE_CHECKING:
    from respecd.config import Profile

MEDIAN_WINDOW_S = 120.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=positive_float, default=10.0, help="how long to run (default 10)")
    parser.add_argument("--every", type=positive_float, default=10.0, metavar="S", help="seconds between samples (10)")
    parser.add_argument("--warmup-min", type=non_negative_float, metavar="M",
                        help="minutes left out of the slope (default: a third of the run, at most 10)")
    parser.add_argument("--config", default="builtin:sim-rover", help="profile to run (default: the simulated rover)")
    parser.add_argument("--record", metavar="DIR", help="also record into DIR (1 GiB cap, oldest files deleted)")


def _proc_status() -> dict[str, int]:
    fields = {}
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "Threads"):
                fields[key] = int(value.split()[0])
    return fields


def sample(pipeline: Any, recorder: Any, t0: float, heap: dict[str, float] | None) -> dict[str, Any]:
    """One row: process resources, queue depths and cumulative drops, now; ``heap`` as read by heap_mb."""
    status = _proc_status()
    queues = {name: q for name, q in pipeline.frame_queues.items()}
    queues.update(bundles=pipeline.bundles, percepts=pipeline.percepts)
    drops = {name: q.dropped for name, q in queues.items()}
    drops["drivers"] = sum(d.health.drops for d in pipeline.drivers.values())
    if recorder is not None:
        drops["recorder"] = recorder.dropped
    return {
        "t_s": round(time.monotonic() - t0, 1),
        "rss_mb": round(status["VmRSS"] / 1024, 1),
        "heap_mb": heap,
        "threads": status["Threads"],
        "python_threads": threading.active_count(),
        "fds": len(os.listdir("/proc/self/fd")),
        "gc_objects": len(gc.get_objects()),
        "queue_depth": {name: len(q) for name, q in queues.items()},
        "drops": drops,
        "load_avg_1m": round(os.getloadavg()[0], 2),
    }


def rss_slope(rows: list[dict[str, Any]], warmup_s: float) -> dict[str, Any]:
    """Least-squares RSS slope (MB/h) after warm-up, its standard error, and 2-minute medians."""
    kept = [r for r in rows if r["t_s"] >= warmup_s]
    if len(kept) < 3:
        return {"samples": len(kept), "slope_mb_per_h": None}
    hours = np.array([r["t_s"] for r in kept]) / 3600.0
    rss = np.array([r["rss_mb"] for r in kept])
    slope, intercept = np.polyfit(hours, rss, 1)
    residual = rss - (slope * hours + intercept)
    spread = float(np.sum((hours - hours.mean()) ** 2))
    stderr = float(np.sqrt(np.sum(residual**2) / (len(kept) - 2) / spread)) if spread > 0 else float("nan")
    first, last = _edges(kept)
    return {
        "samples": len(kept),
        "from_s": kept[0]["t_s"],
        "to_s": kept[-1]["t_s"],
        "slope_mb_per_h": round(float(slope), 2),
        "slope_stderr_mb_per_h": round(stderr, 2),
        "median_first_2min_mb": round(float(np.median([r["rss_mb"] for r in first])), 1),
        "median_last_2min_mb": round(float(np.median([r["rss_mb"] for r in last])), 1),
    }


def _recorder(profile: Profile, directory: str | None, clock: Any) -> Any:
    if directory is None:
        return None
    from respecd.record.recorder import Recorder

    config = profile.recording.model_copy(update={
        "enabled": True, "path": str(Path(directory) / "soak-{time}.mcap"), "rotate_mib": 128.0,
        "max_bytes": 1 << 30, "fsync": False,
    })
    return Recorder(config, profile, clock)


async def _soak(args: argparse.Namespace, state_dir: Path) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    from respecd.clock import MonotonicClock
    from respecd.config import load_profile
    from respecd.daemon import Daemon
    from respecd.drivers.base import DriverContext
    from respecd.session import Session

    profile = load_profile(args.config)
    clock = MonotonicClock()
    recorder = _recorder(profile, args.record, clock)
    session = Session(profile, clock, DriverContext(seed=0, simulation=profile.simulation), state_dir=state_dir,
                      observers=[recorder] if recorder is not None else [])
    rows: list[dict[str, Any]] = []
    t0 = time.monotonic()

    async def sampler() -> None:
        while True:
            # mallinfo2 walks every arena under its lock: off the loop, like the daemon's trim
            heap = await asyncio.to_thread(heap_mb)
            rows.append(sample(session.pipeline, recorder, t0, heap))
            await asyncio.sleep(args.every)

    cpu0 = time.process_time()
    task = asyncio.create_task(sampler(), name="soak-sampler")
    try:
        await Daemon(session, recorder=recorder).run(duration=args.minutes * 60)  # as the daemon: heap trim included
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    extra = {"cpu_percent": round(100 * (time.process_time() - cpu0) / max(time.monotonic() - t0, 1e-9), 1)}
    if recorder is not None:
        extra["recorder"] = recorder.recording_status()
    return rows, extra


def heap_medians(rows: list[dict[str, Any]], warmup_s: float) -> dict[str, Any] | None:
    """C-heap MiB in use and free-but-held, 2-minute medians at the start and end after warm-up.

    Tells a leak (``in_use`` climbs) from the allocator keeping freed blocks (``free_held``
    climbs while ``in_use`` does not); None where the C library cannot say (not glibc).
    """
    kept = [r for r in rows if r["t_s"] >= warmup_s and r.get("heap_mb")]
    if len(kept) < 2:
        return None
    first, last = _edges(kept)
    return {key: {"median_first_2min": round(float(np.median([r["heap_mb"][key] for r in first])), 1),
                  "median_last_2min": round(float(np.median([r["heap_mb"][key] for r in last])), 1)}
            for key in ("in_use", "free_held")}


def _edges(rows: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The samples of the first and of the last MEDIAN_WINDOW_S of ``rows``."""
    return ([r for r in rows if r["t_s"] < rows[0]["t_s"] + MEDIAN_WINDOW_S],
            [r for r in rows if r["t_s"] > rows[-1]["t_s"] - MEDIAN_WINDOW_S])


def summarize(rows: list[dict[str, Any]], warmup_s: float) -> dict[str, Any]:
    """The headline figures of a soak from its samples."""
    hours = max(rows[-1]["t_s"] / 3600.0, 1e-9)
    final = rows[-1]["drops"]
    depth_max = {name: max(r["queue_depth"][name] for r in rows) for name in rows[-1]["queue_depth"]}
    after = [r for r in rows if r["t_s"] >= warmup_s] or rows
    return {
        "rss": rss_slope(rows, warmup_s),
        "heap_mb_after_warmup": heap_medians(rows, warmup_s),
        "rss_mb": {"first": rows[0]["rss_mb"], "max": max(r["rss_mb"] for r in rows), "last": rows[-1]["rss_mb"]},
        "threads_after_warmup": {"min": min(r["threads"] for r in after), "max": max(r["threads"] for r in after)},
        "fds_after_warmup": {"min": min(r["fds"] for r in after), "max": max(r["fds"] for r in after)},
        "gc_objects_after_warmup": {"first": after[0]["gc_objects"], "last": after[-1]["gc_objects"]},
        "queue_depth_max": depth_max,
        "drops_total": final,
        "drops_per_h": {name: round(n / hours, 1) for name, n in final.items()},
        "load_avg_1m": {"first": rows[0]["load_avg_1m"], "max": max(r["load_avg_1m"] for r in rows),
                        "last": rows[-1]["load_avg_1m"]},
    }


def summary(figures: dict[str, Any]) -> str:
    """The lines a person reads; the samples go to --json."""
    rss = figures["rss"]
    lines = [
        f"soak: {figures['minutes']:g} min of {figures['profile']} (recording: {figures['recording']}), "
        f"warm-up {figures['warmup_min']:g} min, load average {figures['load_avg_1m']}",
        f"RSS slope after warm-up: {rss['slope_mb_per_h']} ± {rss.get('slope_stderr_mb_per_h')} MB/h "
        f"({rss['samples']} samples; 2-min medians {rss.get('median_first_2min_mb')} -> "
        f"{rss.get('median_last_2min_mb')} MB)",
        f"C heap MiB after warm-up (2-min medians, first -> last): {_heap_text(figures['heap_mb_after_warmup'])}",
        f"RSS MB: {figures['rss_mb']}   threads: {figures['threads_after_warmup']}   "
        f"fds: {figures['fds_after_warmup']}   gc objects: {figures['gc_objects_after_warmup']}",
        f"queue depth max: {figures['queue_depth_max']}",
        f"drops: {figures['drops_total']}   per hour: {figures['drops_per_h']}   cpu: {figures['cpu_percent']} %",
    ]
    if "recorder" in figures:
        lines.append(f"recorder: {figures['recorder']}")
    return "\n".join(lines)


def _heap_text(heap: dict[str, Any] | None) -> str:
    if heap is None:
        return "not readable here (glibc's mallinfo2 only)"
    return "   ".join(f"{key} {v['median_first_2min']} -> {v['median_last_2min']}" for key, v in heap.items())


def run(args: argparse.Namespace) -> dict[str, Any]:
    check_output_dir("--record", args.record)  # the recorder makes it; a file there would lose the soak's log
    warmup_min = args.warmup_min if args.warmup_min is not None else min(10.0, args.minutes / 3)
    with tempfile.TemporaryDirectory(prefix="respecd-soak-") as state_dir:
        rows, extra = asyncio.run(_soak(args, Path(state_dir)))
    figures: dict[str, Any] = {"minutes": args.minutes, "warmup_min": warmup_min, "profile": args.config,
                               "recording": bool(args.record)}
    figures.update(summarize(rows, warmup_min * 60))
    figures.update(extra)
    figures["samples"] = rows
    return figures
