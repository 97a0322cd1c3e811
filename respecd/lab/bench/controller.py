"""Controller step time: decide+update (p50/p99 µs), state computation, per-percept features.

The controller is built from a profile exactly as the daemon builds it (the profile's
sensors and the simulated drivers' capabilities) and stepped over a seeded stream of
observations that sweeps every state factor, so the table is touched all over rather than
in one hot row. Timings are per call, with ``time.perf_counter_ns``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from respecd.argtypes import positive_int, seed
from respecd.sensors import MAX_RATE_HZ, MIN_RATE_HZ


def rate_levels(text: str) -> tuple[float, ...]:
    """An argparse type: '1,10,30' -> (1.0, 10.0, 30.0), each within the rates a sensor may run
    (the profile's own check, which a model_copy override would skip)."""
    try:
        levels = tuple(float(x) for x in text.split(","))
    except ValueError:
        levels = ()
    if not levels or not all(MIN_RATE_HZ <= r <= MAX_RATE_HZ for r in levels):
        raise argparse.ArgumentTypeError(
            f"expected comma-separated rates from {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz, got {text!r}")
    return levels


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="builtin:sim-rover", help="profile whose sensors define the spaces")
    parser.add_argument("--steps", type=positive_int, default=20000, help="decision steps to time (default 20000)")
    parser.add_argument("--policy", choices=("learn", "exploit", "static", "heuristic"), default="learn")
    parser.add_argument("--mode", choices=("moves", "product", "factored"), default=None,
                        help="override the action mode")
    parser.add_argument("--percepts", type=positive_int, default=2000,
                        help="percepts for the feature/state timing (rounded to tens, at least 10; default 2000)")
    parser.add_argument("--rate-levels", type=rate_levels, default=None,
                        help=f"override the rate levels, e.g. 1,10,30 (Hz, each {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g})")
    parser.add_argument("--seed", type=seed, default=0, help="seed >= 0 (default 0)")


def _percentiles(ns: list[int]) -> tuple[float, float, float]:
    us = np.asarray(ns, dtype=np.float64) / 1000.0
    return float(np.percentile(us, 50)), float(np.percentile(us, 99)), float(us.mean())


def _time(fn: Callable[[Any], Any], inputs: list[Any]) -> list[int]:
    out = []
    for item in inputs:
        t0 = time.perf_counter_ns()
        fn(item)
        out.append(time.perf_counter_ns() - t0)
    return out


def _observations(n: int, seed: int) -> list[Any]:
    from respecd.control.state import Observation

    rng = np.random.default_rng(seed)
    u = rng.random((n, 8))
    contributions = ({"rgb": 0.7, "thermal": 0.2, "radar": 0.1}, {"rgb": 0.1, "thermal": 0.85, "radar": 0.05}, None)
    return [
        Observation(t=float(i), n_percepts=10, illumination=u[i, 0], motion_image=2 + u[i, 1] * 20,
                    motion_imu=u[i, 2] * 0.8, radar_points=u[i, 3] * 40, load=u[i, 4], latency_s=u[i, 5] * 0.2,
                    sync=u[i, 6] * 2, conf_agg=u[i, 7], contributions=contributions[i % 3])
        for i in range(n)
    ]


def _percepts(n: int, seed: int) -> list[Any]:
    from respecd.messages import Bundle, Frame, Health, Modality, Percept, SyncStats

    rng = np.random.default_rng(seed)
    rgb = [rng.integers(0, 256, (720, 1280, 3), dtype=np.uint8) for _ in range(2)]
    radar = rng.normal(size=(24, 5)).astype(np.float32)
    imu = rng.normal(size=6).astype(np.float32)
    percepts = []
    for i in range(n):
        frames: dict[Modality, Frame] = {"rgb": Frame("rgb", i / 10, i, rgb[i % 2]),
                                         "radar": Frame("radar", i / 10, i, radar), "imu": Frame("imu", i / 10, i, imu)}
        bundle = Bundle(i / 10, frames, SyncStats(10.0, 1.0, 0.0, Health.GOOD), i)
        percepts.append(Percept(i / 10, (), 0.5, {"rgb": 0.6, "thermal": 0.4}, 0.05, bundle))
    return percepts


def run(args: argparse.Namespace) -> dict[str, Any]:
    from respecd.clock import MonotonicClock
    from respecd.config import load_profile
    from respecd.control.controller import Controller
    from respecd.control.features import FeatureExtractor, Window
    from respecd.control.probe import SystemProbe
    from respecd.drivers import driver_class

    profile = load_profile(args.profile)
    update: dict[str, Any] = {"policy": args.policy, "seed": args.seed}
    actions: dict[str, Any] = {}
    if args.mode:
        actions["mode"] = args.mode
    if args.rate_levels:
        actions["rate_levels_hz"] = args.rate_levels
    if actions:
        update["actions"] = profile.controller.actions.model_copy(update=actions)
    config = profile.controller.model_copy(update=update)
    clock = MonotonicClock()
    caps = {s.name: driver_class(s.driver)(s, clock).capabilities for s in profile.sensors}  # no I/O in constructors
    controller = Controller.from_profile(config, profile, caps)
    applied = {s.name: s.initial_request() for s in profile.sensors}
    observations = _observations(args.steps, args.seed)
    controller.follow(applied)  # what the sensors run: delivered once, as the control loop does
    step_ns = _time(controller.step, observations)

    window = Window(config.window_s, config.latency_budget_s)
    extractor = FeatureExtractor()
    percepts = _percepts(max(10, args.percepts // 10 * 10), args.seed)
    feature_ns: list[int] = []
    state_ns: list[int] = []
    for start in range(0, len(percepts), 10):  # a decision every 10 percepts (10 Hz, 1 s window)
        feature_ns += _time(lambda p: window.add(extractor.sample(p)), percepts[start:start + 10])
        now = percepts[start + 9].t
        state_ns += _time(lambda t: controller.states.index(controller.states.bins(window.observe(t))), [now])
    probe = SystemProbe()
    probe_ns = _time(lambda _: probe.read(), list(range(200)))

    step = _percentiles(step_ns)
    state = _percentiles(state_ns)
    features = _percentiles(feature_ns)
    probe_p = _percentiles(probe_ns)
    return {
        "step_us_p50": round(step[0], 2),
        "step_us_p99": round(step[1], 2),
        "step_us_mean": round(step[2], 2),
        "state_us_p50": round(state[0], 2),
        "state_us_p99": round(state[1], 2),
        "features_us_p50": round(features[0], 2),
        "features_us_p99": round(features[1], 2),
        "probe_us_p50": round(probe_p[0], 2),
        "steps": args.steps,
        "policy": config.policy,
        "action_mode": config.actions.mode,
        "states": controller.states.size,
        "actions": controller.space.n,
        "table_columns": controller.space.columns,
        "profile": profile.name,
    }
