"""Live view: event-loop lag of the simulated rover with ``--foxglove`` off, with a client
subscribed to every channel, and with a client too slow to keep up.

The rover runs at its profile rates (detector off, so the loop's own lag is what is
measured). The client is a separate process (the ``websockets`` package, subprotocol
``foxglove.websocket.v1``): it subscribes to every advertised channel and reads as fast as
it can, or one message every ``--slow-read-s``. Figures: loop lag p50/p99 (a 5 ms probe's
lateness), sync jitter p99, the recorder's drops, messages the client got, process CPU.
"""

from __future__ import annotations

import argparse
import asyncio
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from respecd.argtypes import MAX_PORT, non_negative_float, port_number, positive_float
from respecd.lab.bench.pipeline import timed_run

CLIENT = r"""
import asyncio, json, sys, time
import websockets
port, seconds, pause = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
async def main():
    end = time.time() + seconds
    got = 0
    while time.time() < end:
        try:
            async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"],
                                          max_size=None) as ws:
                seen = set()
                while time.time() < end:
                    m = await asyncio.wait_for(ws.recv(), max(0.1, end - time.time()))
                    if isinstance(m, str):
                        j = json.loads(m)
                        new = [c["id"] for c in j.get("channels", []) if c["id"] not in seen]
                        if j.get("op") == "advertise" and new:
                            seen.update(new)
                            subs = [{"id": c, "channelId": c} for c in new]
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                    else:
                        got += 1
                        if pause:
                            await asyncio.sleep(pause)
        except (OSError, asyncio.TimeoutError, websockets.ConnectionClosed):
            await asyncio.sleep(0.2)
    print(got)
asyncio.run(main())
"""


def first_port(text: str) -> int:
    """An argparse type: the fast client's port; the slow client's run uses the next one, so both must exist."""
    try:
        port = port_number(text)
    except argparse.ArgumentTypeError:
        port = 0
    if not 1 <= port < MAX_PORT:
        raise argparse.ArgumentTypeError(f"expected a port from 1 to {MAX_PORT - 1} (the slow-client run uses "
                                         f"PORT + 1), got {text!r}")
    return port


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=positive_float, default=15.0, help="length of each run (default 15 s)")
    parser.add_argument("--slow-read-s", type=non_negative_float, default=0.5,
                        help="the slow client's pause per message (s, default 0.5)")
    parser.add_argument("--port", type=first_port, default=28871,
                        help=f"port of the live view, 1..{MAX_PORT - 1}; the slow-client run uses PORT + 1 "
                             "(default 28871)")


def _profile() -> Any:
    from respecd.config import load_profile

    profile = load_profile("builtin:sim-rover")
    return profile.model_copy(update={
        "perception": profile.perception.model_copy(update={"enabled": False}),
        "controller": profile.controller.model_copy(update={"enabled": False}),
    })


async def _run(seconds: float, port: int | None) -> dict[str, Any]:
    from respecd.clock import MonotonicClock
    from respecd.daemon import Daemon
    from respecd.drivers.base import DriverContext
    from respecd.record import make_recorder
    from respecd.session import Session

    profile = _profile()
    clock = MonotonicClock()
    recorder = make_recorder(profile, None, clock, f"127.0.0.1:{port}") if port else None
    with tempfile.TemporaryDirectory() as state_dir:
        session = Session(profile, clock, DriverContext(seed=0, simulation=profile.simulation),
                          state_dir=Path(state_dir), observers=[recorder] if recorder else [])
        jitter, lag, cpu_s, wall_s = await timed_run(Daemon(session, recorder=recorder), seconds)
    warm_lag, warm_jitter = lag[len(lag) // 10 :], np.abs(jitter[len(jitter) // 10 :])
    return {
        "loop_lag_ms_p50": round(float(np.percentile(warm_lag, 50)) * 1000, 3),
        "loop_lag_ms_p99": round(float(np.percentile(warm_lag, 99)) * 1000, 3),
        "sync_jitter_ms_p99": round(float(np.percentile(warm_jitter, 99)) * 1000, 3),
        "recorder_dropped": recorder.dropped if recorder else 0,
        "cpu_percent_of_one_core": round(100.0 * cpu_s / wall_s, 1),
    }


def _with_client(seconds: float, port: int, pause: float) -> dict[str, Any]:
    client = subprocess.Popen([sys.executable, "-c", CLIENT, str(port), str(seconds + 3), str(pause)],
                              stdout=subprocess.PIPE, text=True)
    try:
        figures = asyncio.run(_run(seconds, port))
    finally:
        out, _ = client.communicate(timeout=seconds + 30)
    figures["client_messages"] = int(out.strip() or 0)
    return figures


def run(args: argparse.Namespace) -> dict[str, Any]:
    import os

    return {
        "load_average_before": [round(x, 2) for x in os.getloadavg()],
        "live_off": asyncio.run(_run(args.seconds, None)),
        "live_fast_client": _with_client(args.seconds, args.port, 0.0),
        "live_slow_client": _with_client(args.seconds, args.port + 1, args.slow_read_s),
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
    }
