"""Replay: ``--speed max`` throughput with the detector, and recording overhead at 30 Hz.

* Recording overhead: the recorder taps real simulated frames (pre-rendered, cycled) on a
  real-time 30 Hz schedule; overhead = CPU time of the writer thread (encode, compress,
  write) plus the taps on the loop, over wall time, in % of one core. Measured for RGB
  alone (640x360 at 30 Hz) and for the whole simulated rover at its profile rates, as the
  sim-rover profile records (its ``recording:`` section: RGB JPEG, thermal and depth
  lossless PNG, lz4 chunks), and once with zstd chunks.
* Replay throughput: a simulated session is recorded in lockstep (fast, no detector), then
  replayed with ``--speed max`` through the full pipeline with the detector, RGB held at
  the chosen resolution (policy static, one RGB setting) (``replay_speed_x``); the same
  inferences (the frames each one ran on, attributed or not) again through the detector
  alone, one after another (``detector_only_speed_x``: the most the replay could reach);
  and the replay once more without the detector (``pipeline_only_speed_x``: the replay
  machinery alone). Speed = log seconds / wall seconds of the replay loop (imports, profile
  and weight loading are ``startup_s``). The log has no percepts, so perception is paced by
  the default latency model (the detector's measured cost here).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from respecd.argtypes import non_negative_int, positive_float, resolution, seed
from respecd.errors import InputError
from respecd.outputs import check_output_dir
from respecd.record.simulated import record_simulated

if TYPE_CHECKING:
    from respecd.config import Profile

LOGS = ("rgb-only.mcap", "rover.mcap", "rover-zstd.mcap", "session.mcap")  # what --keep keeps


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=positive_float, default=20.0,
                        help="length of the simulated log to replay (s)")
    parser.add_argument("--resolution", default="640x360", help="RGB resolution WxH (default 640x360)")
    parser.add_argument("--weights", default="builtin:sim-rover", help="detector checkpoint (default the shipped one)")
    parser.add_argument("--record-seconds", type=positive_float, default=10.0,
                        help="real-time recording measurement (s)")
    parser.add_argument("--seed", type=seed, default=0, help="simulator seed >= 0")
    parser.add_argument("--torch-threads", type=non_negative_int, default=0,
                        help="detector threads for the replay (default: the profile's, 1)")
    parser.add_argument("--keep", metavar="DIR", help="keep the generated log and report in DIR")


def run(args: argparse.Namespace) -> dict[str, Any]:
    check_output_dir("--keep", args.keep)  # made below with its parents
    taken = [n for n in LOGS if args.keep and (Path(args.keep) / n).exists()]
    if taken:  # recordings are never overwritten, not even this benchmark's own from an earlier run
        raise InputError(f"--keep {args.keep}: {Path(args.keep) / taken[0]} exists; expected a folder without "
                         f"{', '.join(LOGS)} (a new one, or remove them)")
    width, height = resolution(args.resolution, "--resolution")
    _check_weights(args.weights)  # a bad file is exit 2 now, not after the recording phase
    with tempfile.TemporaryDirectory(prefix="respecd-bench-replay-") as scratch:
        work = Path(args.keep) if args.keep else Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        size = (width, height)
        rgb_only = asyncio.run(_recording_overhead(work / "rgb-only.mcap", size, args, rgb_only=True))
        rover = asyncio.run(_recording_overhead(work / "rover.mcap", size, args, rgb_only=False))
        rover_zstd = asyncio.run(_recording_overhead(work / "rover-zstd.mcap", size, args, False, "zstd"))
        profile, weights_note = _profile(args, (width, height), work)
        log = record_simulated(profile, work / "session.mcap", args.seconds, args.seed)
        inferences: list[tuple[dict[str, Any], bool]] = []
        replay = _replay(profile, log, work, args, observe=_capture(profile, inferences))
        alone = detector_only(profile, inferences, replay["log_s"])
        inferences.clear()
        no_detector = profile.model_copy(
            update={"perception": profile.perception.model_copy(update={"enabled": False})}
        )
        replay_core = _replay(no_detector, log, work / "core", args)
    return {
        "replay_speed_x": replay["x_realtime"],
        "detector_only_speed_x": alone["x_realtime"],
        "pipeline_only_speed_x": replay_core["x_realtime"],
        "startup_s": replay["startup_s"],
        "replay_over_detector_only": round(replay["x_realtime"] / alone["x_realtime"], 3),
        "recording_rgb_30hz": rgb_only,
        "recording_sim_rover": rover,
        "recording_sim_rover_zstd": rover_zstd,
        "replay": {**replay, "weights": weights_note, "rgb": f"{width}x{height}",
                   "torch_threads": profile.perception.torch_threads},
        "detector_only": alone,
        "replay_without_detector": replay_core,
    }


# -- recording overhead -------------------------------------------------------------------
def _frames(size: tuple[int, int], seed: int) -> dict[str, list[Any]]:
    """Real simulated frames per modality (the sim-rover's resolutions), 15 of each."""
    import numpy as np

    from respecd.sim.render import render_depth, render_imu, render_radar, render_rgb, render_thermal
    from respecd.sim.world import SimulationConfig, World

    world = World(SimulationConfig(scenarios=["good-light-moving"]), seed)
    rng = np.random.default_rng(seed)
    out: dict[str, list[Any]] = {"rgb": [], "thermal": [], "radar": [], "depth": [], "imu": []}
    for k in range(15):
        state = world.state_at(5.0 + k / 30)
        out["rgb"].append(render_rgb(state, size, 1 / 30, rng))
        out["thermal"].append(render_thermal(state, (160, 120), rng))
        out["radar"].append(render_radar(state, "range", 10.0, rng))
        out["depth"].append(render_depth(state, (640, 480), rng))
        out["imu"].append(render_imu(state, rng))
    return out


async def _recording_overhead(
    path: Path, size: tuple[int, int], args: argparse.Namespace, rgb_only: bool, compression: str | None = None
) -> dict:
    from respecd.clock import MonotonicClock
    from respecd.config import load_profile
    from respecd.messages import Frame
    from respecd.record.recorder import Recorder

    rates = {"rgb": 30.0} if rgb_only else {"rgb": 30.0, "thermal": 9.0, "radar": 10.0, "depth": 15.0, "imu": 30.0}
    frames = _frames(size, args.seed)
    clock = MonotonicClock()
    # the sim-rover's profile: its recording section, calibrations and extrinsics, as in the daemon
    profile = load_profile("builtin:sim-rover")
    config = profile.recording.model_copy(update={"enabled": True, "path": str(path)})
    if compression is not None:
        config = config.model_copy(update={"compression": compression})
    recorder = Recorder(config, profile, clock)
    recorder.start()
    tap_cpu = 0.0
    counts = dict.fromkeys(rates, 0)
    start = clock.now()
    tick = 1.0 / 30
    k = 0
    while clock.now() - start < args.record_seconds:
        k += 1
        await clock.sleep_until(start + k * tick)
        now = clock.now()
        c0 = time.thread_time()
        for name, rate in rates.items():
            if counts[name] < (now - start) * rate:
                data = frames[name][counts[name] % 15]
                recorder.on_frame(name, Frame(name, now, counts[name], data))  # type: ignore[arg-type]
                counts[name] += 1
        tap_cpu += time.thread_time() - c0
    wall = clock.now() - start
    await recorder.close()
    cpu = recorder.cpu_s + tap_cpu
    return {
        "streams_hz": rates,
        "compression": config.compression,
        "encodings": {"rgb": config.rgb_format, "thermal": config.thermal_format, "depth": config.depth_format},
        "jpeg_quality": config.jpeg_quality,
        "wall_s": round(wall, 2),
        "frames": sum(counts.values()),
        "writer_cpu_s": round(recorder.cpu_s, 3),
        "tap_cpu_s": round(tap_cpu, 4),
        "overhead_pct_of_one_core": round(100 * cpu / wall, 2),
        "dropped": recorder.dropped,
        "mib_per_s": round(path.stat().st_size / 2**20 / wall, 2),
    }


# -- replay throughput --------------------------------------------------------------------
def _check_weights(weights: str) -> None:
    """ConfigError for a checkpoint that cannot be loaded; a built-in one that does not ship is fine
    (``_profile`` takes an untrained net of the same shape)."""
    from respecd.errors import ConfigError
    from respecd.perception import checkpoint

    try:
        path = checkpoint.resolve(weights)
    except ConfigError:
        if weights.startswith("builtin:"):
            return
        raise
    checkpoint.spec_of(str(path))


def _profile(args: argparse.Namespace, size: tuple[int, int], work: Path) -> tuple[Any, str]:
    """sim-rover with RGB fixed at ``size``, policy static; untrained weights when none ship."""
    from respecd.config import load_profile
    from respecd.errors import ConfigError
    from respecd.perception import checkpoint

    weights, note = args.weights, args.weights
    try:
        checkpoint.resolve(weights)
    except ConfigError:
        from respecd.perception.model import FusionNet

        profile = load_profile("builtin:sim-rover")
        weights = str(work / "untrained.pt")
        checkpoint.save(Path(weights), FusionNet(profile.perception.model))
        note = f"untrained (no checkpoint {args.weights!r}); same network, so the same compute"
    base = load_profile("builtin:sim-rover")
    sensors = [s.model_copy(update={"resolution": size}) if s.modality == "rgb" else s for s in base.sensors]
    actions = base.controller.actions.model_copy(update={"rgb_resolutions": (size,)})
    controller = base.controller.model_copy(update={"policy": "static", "actions": actions})
    perception = base.perception.model_copy(update={"weights": weights})
    if args.torch_threads:
        perception = perception.model_copy(update={"torch_threads": args.torch_threads})
    return base.model_copy(update={"sensors": sensors, "controller": controller, "perception": perception}), note


def _replay(profile: Profile, log: Path, work: Path, args: argparse.Namespace, observe: Any = None) -> dict[str, Any]:
    import json

    import yaml

    from respecd.replay.run import replay

    work.mkdir(parents=True, exist_ok=True)
    config = work / "replay-profile.yaml"
    config.write_text(yaml.safe_dump(profile.model_dump(mode="json")))
    report = work / "replay-report.json"
    start = time.perf_counter()
    replay(log, config=config, policy="static", speed="max", seed=args.seed, report=report, observe=observe)
    total = time.perf_counter() - start
    entry = json.loads(report.read_text())["policies"]["static"]
    timing = entry["timing"]
    return {
        "log_s": entry["replayed_s"],
        "loop_wall_s": timing["wall_s"],
        "x_realtime": round(entry["replayed_s"] / timing["wall_s"], 2),
        "loop_cpu_s": timing["cpu_s"],
        "loop_thread_cpu_s": timing.get("loop_cpu_s"),
        "x_realtime_per_cpu_s": round(entry["replayed_s"] / timing["cpu_s"], 2),
        "load_average_1min": round(os.getloadavg()[0], 2),
        "latency_model": entry["latency_model"],
        "startup_s": round(total - timing["wall_s"], 2),  # imports, weights, log pre-scan, report
        "percepts": entry["compute"]["percepts"],
        "attributions": entry["compute"]["attributions"],
        "inference_ms_per_log_s": timing["inference_ms_per_s"],
        "mean_latency_ms": timing["mean_latency_ms"],
    }


def _capture(profile: Profile, into: list[tuple[dict[str, Any], bool]]) -> Any:
    """A replay observer keeping each inference's detector inputs and whether it attributed."""
    inputs = {"rgb", *profile.perception.model.aux_modalities}

    def observe(session: Any) -> None:
        def keep(percept: Any) -> None:
            frames = percept.bundle.frames if percept.bundle is not None else {}
            into.append(({m: f for m, f in frames.items() if m in inputs}, percept.contributions is not None))

        session.hooks.inference.append(keep)

    return observe


def detector_only(profile: Profile, inferences: list[tuple[dict[str, Any], bool]], log_s: float) -> dict[str, Any]:
    """The replay's inferences again, through the detector alone: same frames, same
    attributions, same checkpoint and thread count, one after another on this thread."""
    from respecd.perception.detector import FusionDetector
    from respecd.perception.stage import calibration_from_profile

    detector = FusionDetector.load(profile.perception, calibration_from_profile(profile))
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for frames, attribute in inferences:
        detector.infer(frames, attribute)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return {
        "inferences": len(inferences),
        "attributions": sum(attribute for _, attribute in inferences),
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "x_realtime": round(log_s / wall, 2) if wall > 0 else None,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
